"""PairCorrections on tiny tensors, without training: fitted once from a fake render, applied, saved and loaded."""

from __future__ import annotations

import dataclasses
import io
import math
from collections.abc import Callable
from typing import Any

import numpy as np
import pandas as pd
import pytest
import torch

from rflscm.errors import CheckpointError
from rflscm.models.pairs import PairData
from rflscm.models.rflscm import corrections as corrections_module
from rflscm.models.rflscm.config import CorrectionsConfig
from rflscm.models.rflscm.corrections import PairCorrections, fit_corrections
from rflscm.models.rflscm.posterior import WNOMP_ATOMS, PairPosterior

K = 4  # bins; every beam sees every bin with gain 1, so a pair's prediction is the sum of its APS


def data(rsrp: list[list[float]], cells: list[int]) -> PairData:
    r = torch.tensor(rsrp, dtype=torch.float32)
    p, m = r.shape
    return PairData(
        cell_index=torch.tensor(cells),
        grid_ids=np.arange(100, 100 + p, dtype=np.int64),
        grid_xyz=torch.zeros(p, 3),
        rsrp=r,
        beam_mask=torch.ones(p, m, dtype=torch.bool),
        val_mask=torch.zeros(p, m, dtype=torch.bool),
        x_scale=torch.ones(p),
        bound=torch.full((p, m), float("nan")),
        val_pairs=torch.zeros(0, dtype=torch.long),
    )


def render(aps: torch.Tensor, calls: list[torch.Tensor]):
    def fn(pairs: torch.Tensor):
        calls.append(pairs.clone())
        x = aps[pairs]
        bins = torch.arange(K).expand(len(pairs), K)
        return bins, x, x.sum(1, keepdim=True).expand(-1, 2).clone()  # two beams: SSB (0), CSI-RS (1)

    return fn


def columns(cells: torch.Tensor, bins: torch.Tensor) -> torch.Tensor:
    return torch.ones(len(cells), 2, bins.shape[1])


# pair 0: measured 10x the prediction on both beams (+10 dB); pair 1: exact; both in cell 0; pair 2 in cell 1 at +3 dB
APS = torch.full((3, K), 0.25)
RSRP = [[10.0, 10.0], [1.0, 1.0], [10**0.3, 10**0.3]]


def test_levels_and_anchors_are_fitted_from_one_render_and_centre_each_pair() -> None:
    calls: list[torch.Tensor] = []
    cfg = CorrectionsConfig(pair_posterior=False)
    fitted = fit_corrections(cfg, data(RSRP, [0, 0, 1]), 1, np.array([7, 8]), render(APS, calls), columns, seed=0)
    assert len(calls) == 1 and calls[0].tolist() == [0, 1, 2]  # one render of every pair with reports
    assert fitted.levels is not None and fitted.posterior is None
    # fewer than LEVEL_MIN_BEAMS beams per cell: every cell takes the median over all cells (pairs at 10, 0, 3 dB)
    torch.testing.assert_close(fitted.levels, torch.full((2, 2), 3.0), atol=1e-4, rtol=0)
    anchors = fitted.anchors
    assert anchors is not None
    np.testing.assert_allclose(anchors.loc[[(7, 100), (7, 101), (8, 102)]].to_numpy(), [7.0, -3.0, 0.0], atol=1e-4)
    out = fitted.apply(
        torch.full((4, K), 0.25), np.array([0, 0, 1, 1]), np.array([7, 7, 8, 8]), np.array([100, 101, 102, 999])
    )
    # level and anchor together restore each pair's measured power; an unmeasured grid gets the level alone
    np.testing.assert_allclose(out.sum(1).numpy(), [10.0, 1.0, 10**0.3, 10**0.3], rtol=1e-4)


def test_switches_off_fit_nothing_and_change_nothing() -> None:
    calls: list[torch.Tensor] = []
    off = CorrectionsConfig(calibrate_levels=False, pair_anchors=False, pair_posterior=False)
    fitted = fit_corrections(off, data(RSRP, [0, 0, 1]), 1, np.array([7, 8]), render(APS, calls), columns, seed=0)
    assert not calls and fitted == PairCorrections()
    assert torch.equal(fitted.apply(APS, np.array([0]), np.array([7]), np.array([100])), APS)
    assert fitted.level_offset_db(np.array([0]), "csi") is None


def test_the_csi_offset_is_relative_to_the_ssb_level() -> None:
    fitted = PairCorrections(levels=torch.tensor([[1.0, 4.0], [2.0, 0.5]]))
    np.testing.assert_allclose(fitted.level_offset_db(np.array([1, 0]), "csi"), [-1.5, 3.0])
    assert fitted.level_offset_db(np.array([1, 0]), "ssb") is None


def test_a_round_trip_through_torch_save_with_weights_only_keeps_every_part() -> None:
    index = pd.MultiIndex.from_arrays([np.array([7, 8]), np.array([100, 102])], names=["cell_id", "grid_id"])
    posterior = PairPosterior(
        index, torch.tensor([[0, 1], [2, 3]]), torch.tensor([[1.0, -2.0], [0.5, 0.0]]), 1.0, {1.0: 0.5}
    )
    fitted = PairCorrections(torch.tensor([[1.0, 2.0], [3.0, 4.0]]), pd.Series([0.5, -1.0], index=index), posterior)
    buffer = io.BytesIO()
    torch.save(fitted.to_state(), buffer)
    buffer.seek(0)
    loaded = PairCorrections.from_state(torch.load(buffer, weights_only=True), num_bins=K)
    aps = torch.rand(3, K)
    args = (np.array([0, 1, 1]), np.array([7, 8, 8]), np.array([100, 102, 5]))
    torch.testing.assert_close(loaded.apply(aps, *args), fitted.apply(aps, *args))
    assert PairCorrections.from_state(None, K) == PairCorrections()
    with pytest.raises(CheckpointError, match="pair corrections are damaged"):
        PairCorrections.from_state([1, 2], K)  # type: ignore[arg-type]


def timed_problem(num: int, num_cells: int, seed: int):
    """``num`` pairs over ``num_cells`` cells measured near their APS sum (±1 dB noise), and a render that charges
    10 ms of a fake clock (``now``) per pair: ``(rsrp, cells, render, now)``."""
    gen = torch.Generator().manual_seed(seed)
    aps = torch.rand(num, K, generator=gen) + 0.1
    rsrp = (aps.sum(1, keepdim=True) * 10 ** (torch.randn(num, 2, generator=gen) / 10)).tolist()
    now = [0.0]

    def costly(pairs: torch.Tensor):
        now[0] += 0.01 * pairs.numel()
        return render(aps, [])(pairs)

    return rsrp, [i % num_cells for i in range(num)], costly, now


def test_within_a_deadline_the_pass_corrects_the_pairs_that_fit_and_the_rest_keep_the_level(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Every rendered pair costs 10 ms of a fake clock. The level's pairs come first, then chunks of the others while the
    slowest chunk so far (× CHUNK_MARGIN) still fits; pairs left over have no anchor; with time enough, every pair
    gets the anchor a pass without a deadline gives it (its own mean: the pull toward the cell's mean, measured on
    the pairs a pass corrects, is left out here; its own tests are in test_anchors.py)."""
    from rflscm.models.rflscm.corrections import LEVEL_PAIRS_PER_CELL, PAIR_CHUNK

    monkeypatch.setattr(corrections_module, "shrunk_anchors", lambda anchor, *_: (anchor, math.nan))

    num = 200
    rsrp, cells, costly, now = timed_problem(num, 2, seed=1)

    cfg = CorrectionsConfig(pair_posterior=False)
    args = (cfg, data(rsrp, cells), 1, np.array([7, 8]), costly, columns)
    full = fit_corrections(*args, seed=0)
    assert full.anchors is not None and len(full.anchors) == num
    now[0] = 0.0
    # one pair per cell (0.02 s), the level's other 30 (0.3 s), one chunk of 64 (0.64 s); a second does not fit
    cut = fit_corrections(*args, seed=0, time_left=lambda: 1.7 - now[0], clock=lambda: now[0])
    assert cut.anchors is not None and cut.corrected_pairs() == 2 * LEVEL_PAIRS_PER_CELL + PAIR_CHUNK
    assert set(cut.anchors.index) <= set(full.anchors.index)
    np.testing.assert_allclose(cut.anchors.to_numpy(), full.anchors.loc[cut.anchors.index].to_numpy(), atol=1e-5)
    torch.testing.assert_close(cut.levels, full.levels)  # the level's pairs are always in
    uncorrected = sorted(set(full.anchors.index) - set(cut.anchors.index))[:3]
    ids, grids = (np.array(v) for v in zip(*uncorrected))
    out = cut.apply(torch.full((3, K), 0.25), ids - 7, ids, grids)
    assert cut.levels is not None
    torch.testing.assert_close(out[:, 0], 0.25 * 10 ** (cut.levels[ids - 7, 0] / 10))  # the level only
    now[0] = 0.0
    ample = fit_corrections(*args, seed=0, time_left=lambda: 1e9 - now[0], clock=lambda: now[0])
    assert ample.anchors is not None
    pd.testing.assert_series_equal(ample.anchors.sort_index(), full.anchors.sort_index(), atol=1e-5)


def test_a_pass_that_renders_what_it_leaves_corrects_while_the_rest_still_fits_and_renders_the_rest() -> None:
    """With ``render_rest`` (a caller would render the pairs the pass leaves) and no fallback to answer them (no
    visible bins), the pass corrects a chunk only while the time left still renders every pair left after it, then
    renders and keeps the rest with their level only, all within its deadline: every pair then has a kept render and
    the corrected ones their anchors. Without it, the pass corrects what fits and renders nothing more; with a
    deadline too short to render them all it renders what fits."""
    from rflscm.models.rflscm.corrections import LEVEL_PAIRS_PER_CELL

    rsrp, cells, costly, now = timed_problem(400, 2, seed=1)
    args = (CorrectionsConfig(pair_posterior=False), data(rsrp, cells), 1, np.array([7, 8]), costly, columns)

    def run(deadline: float, rest: bool) -> PairCorrections:
        now[0] = 0.0
        return fit_corrections(
            *args, seed=0, time_left=lambda: deadline - now[0], clock=lambda: now[0], render_rest=rest
        )  # fmt: skip

    every = run(5.0, True)  # 400 renders of 10 ms fit
    assert every.fallback is None and every.anchors is not None and every.rendered is not None
    assert len(every.rendered.index) == 400 and set(every.anchors.index) <= set(every.rendered.index)
    assert now[0] <= 5.0
    short = run(2.5, True)  # 224 renders fit: the levels' 32 pairs corrected, the rest rendered with the level only
    assert short.rendered is not None and short.anchors is not None and now[0] <= 2.5
    assert short.corrected_pairs() == 2 * LEVEL_PAIRS_PER_CELL < len(short.rendered.index) < 400
    assert set(short.anchors.index) < set(short.rendered.index)
    alone = run(2.5, False)  # the same deadline spent on corrections only: nothing rendered beyond them
    assert alone.rendered is not None and len(alone.rendered.index) == alone.corrected_pairs()
    assert alone.corrected_pairs() > short.corrected_pairs()


def test_the_pass_keeps_the_render_of_every_pair_it_corrects_and_a_save_keeps_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Each corrected pair's render is kept whole (bins and values as the render gave them), for those pairs only;
    none where the render is wider than ``KEPT_BINS`` (HiTAM's warm-up spreads the coarse APS over every bin)."""
    from rflscm.models.rflscm import corrections as C

    rsrp, cells, costly, now = timed_problem(200, 2, seed=1)
    args = (CorrectionsConfig(pair_posterior=False), data(rsrp, cells), 1, np.array([7, 8]), costly, columns)
    cut = fit_corrections(*args, seed=0, time_left=lambda: 1.7 - now[0], clock=lambda: now[0])
    kept = cut.rendered
    assert kept is not None and cut.anchors is not None
    assert set(kept.index) == set(cut.anchors.index) and len(kept.index) < 200
    rows = np.array([g for _, g in kept.index]) - 100
    gen = torch.Generator().manual_seed(1)  # timed_problem's APS, drawn again
    aps = torch.rand(200, K, generator=gen) + 0.1
    torch.testing.assert_close(kept.gains, aps[torch.as_tensor(rows)])
    assert (kept.bins == torch.arange(K)).all()
    ids, grids = np.array([c for c, _ in kept.index]), np.array([g for _, g in kept.index])
    assert (cut.stored_rows(ids, grids) == np.arange(len(rows))).all()
    assert (cut.stored_rows(np.array([7]), np.array([99999])) == -1).all()
    buffer = io.BytesIO()
    torch.save(cut.to_state(), buffer)
    buffer.seek(0)
    loaded = PairCorrections.from_state(torch.load(buffer, weights_only=True), K)
    assert loaded.rendered is not None and loaded.rendered.index.equals(kept.index)
    torch.testing.assert_close(loaded.rendered.gains, kept.gains)
    monkeypatch.setattr(C, "KEPT_BINS", K - 1)
    now[0] = 0.0
    assert fit_corrections(*args, seed=0, time_left=lambda: 1.7 - now[0], clock=lambda: now[0]).rendered is None


def test_a_pass_past_its_budget_corrects_no_pair_beyond_its_least() -> None:
    """``extra_left`` is the time left for the pairs beyond the least (the levels' pairs and the fallback): a pass
    that runs past its budget's end to keep its least (``extra_left`` ≤ 0) corrects the levels' pairs only, though its
    ``time_left`` would fit another chunk; with time to spare there it corrects as without it."""
    from rflscm.models.rflscm.corrections import LEVEL_PAIRS_PER_CELL, PAIR_CHUNK

    rsrp, cells, costly, now = timed_problem(200, 2, seed=1)
    args = (CorrectionsConfig(pair_posterior=False), data(rsrp, cells), 1, np.array([7, 8]), costly, columns)
    for extra, expected in ((-1.0, 2 * LEVEL_PAIRS_PER_CELL), (1.7, 2 * LEVEL_PAIRS_PER_CELL + PAIR_CHUNK)):
        now[0] = 0.0
        cut = fit_corrections(
            *args, seed=0, time_left=lambda: 1.7 - now[0], clock=lambda: now[0], extra_left=lambda e=extra: e - now[0]
        )  # fmt: skip
        assert cut.corrected_pairs() == expected


def test_a_pass_with_the_time_for_every_pair_corrects_every_pair_though_its_first_pairs_cost_more() -> None:
    """A correction's columns cost a cell's set-up per chunk (50 ms of the fake clock for each cell a chunk spans), so
    the first pairs, one per cell, cost several times what a later chunk's pairs do.  Given 15 % more than the whole
    pass takes, the pass corrects every pair: a later chunk is priced by the later chunks' own cost (priced by the
    first pairs' cost, the pass left 17 pairs uncorrected with 40 % of its time unspent, as etoile's ideal demo did
    under load)."""
    num, num_cells = 600, 8
    rsrp, cells, costly, now = timed_problem(num, num_cells, seed=3)

    def cell_columns(c: torch.Tensor, bins: torch.Tensor) -> torch.Tensor:
        now[0] += 0.05 * c.unique().numel()
        return columns(c, bins)

    cfg = CorrectionsConfig(wnomp_atoms=False, wnomp_fallback=False)
    args = (cfg, data(rsrp, cells), 1, np.arange(7, 7 + num_cells), costly, cell_columns)
    now[0] = 0.0
    ample = fit_corrections(*args, seed=0, time_left=lambda: 1e9 - now[0], clock=lambda: now[0])
    whole = now[0]
    assert ample.corrected_pairs() == num
    now[0] = 0.0
    fitted = fit_corrections(*args, seed=0, time_left=lambda: 1.15 * whole - now[0], clock=lambda: now[0])
    assert fitted.corrected_pairs() == num and now[0] <= 1.15 * whole
    now[0] = 0.0  # short of it: the pass stops before the deadline
    cut = fit_corrections(*args, seed=0, time_left=lambda: 0.4 * whole - now[0], clock=lambda: now[0])
    assert cut.corrected_pairs() < num and now[0] <= 0.4 * whole


def test_short_of_time_lambdas_pairs_shrink_before_the_levels_pairs(monkeypatch: pytest.MonkeyPatch) -> None:
    """The levels are measured on every cell's full share of pairs while λ's pairs shrink: a level measured on one
    pair per cell was off by 15 dB on CSI-RS in a tile of the 37-site network (DECISIONS)."""
    import rflscm.models.rflscm.corrections as module
    from rflscm.models.rflscm.corrections import LEVEL_PAIRS_PER_CELL, PAIR_CHUNK

    rsrp, cells, costly, now = timed_problem(1200, 4, seed=2)

    seen: dict[str, int] = {}
    first_pairs = module._first_pairs

    def spy(fit, *args, **kwargs):  # type: ignore[no-untyped-def]
        out = first_pairs(fit, *args, **kwargs)
        seen.update(per_cell=fit.level_per_cell, lam_pairs=int(out[2].numel()))
        return out

    monkeypatch.setattr(module, "_first_pairs", spy)
    cfg = CorrectionsConfig(wnomp_atoms=False, wnomp_fallback=False)
    args = (cfg, data(rsrp, cells), 1, np.array([7, 8, 9, 10]), costly, columns)
    # room for the levels' 4 x 16 pairs and ~100 of λ's, not for its 512: λ's shrink, the levels' do not
    fit_corrections(*args, seed=0, time_left=lambda: 4.0 - now[0], clock=lambda: now[0])
    assert seen["per_cell"] == LEVEL_PAIRS_PER_CELL
    assert PAIR_CHUNK <= seen["lam_pairs"] < 200
    # room for less than the levels' pairs: fewer per cell, λ's at their least
    now[0] = 0.0
    fit_corrections(*args, seed=0, time_left=lambda: 1.5 - now[0], clock=lambda: now[0])
    assert 1 <= seen["per_cell"] < LEVEL_PAIRS_PER_CELL and PAIR_CHUNK <= seen["lam_pairs"] < 100


def atom_problem(seed: int = 0, pairs: int = 48, beams: int = 16, bins: int = 40, field_bins: int = 6):
    """Pairs whose true APS is one strong atom the field's bins miss (the field spreads its power over other bins).

    Returns the training data, a render of the field, the columns of two cells, the true APS and a second
    (round-2) sensing matrix per cell that the corrected APS is judged with."""
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(2, beams, bins, generator=g) ** 3  # two cells' normalised sensing matrices
    a2 = torch.rand(2, beams, bins, generator=g) ** 3  # their changed antennas'
    cells = torch.arange(pairs) % 2
    truth = torch.zeros(pairs, bins)
    atom = torch.randint(field_bins, bins, (pairs,), generator=g)  # never among the field's bins
    truth[torch.arange(pairs), atom] = 1.0 + torch.rand(pairs, generator=g)
    truth[:, :field_bins] += 0.05 * torch.rand(pairs, field_bins, generator=g)  # the field's bins carry a little
    rsrp = torch.einsum("bmn,bn->bm", a[cells], truth)
    field_x = truth[:, :field_bins].sum(1, keepdim=True) + truth.sum(1, keepdim=True) / field_bins
    field_x = field_x.expand(-1, field_bins) * (0.5 + torch.rand(pairs, field_bins, generator=g))

    def render(p: torch.Tensor):
        bins_ = torch.arange(field_bins).expand(len(p), field_bins)
        x = field_x[p]
        return bins_, x, torch.einsum("bmk,bk->bm", a[cells[p]][:, :, :field_bins], x)

    def columns(c: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return torch.gather(a[c], 2, b[:, None, :].expand(-1, beams, -1))

    pair_data = PairData(
        cell_index=cells,
        grid_ids=np.arange(pairs, dtype=np.int64),
        grid_xyz=torch.zeros(pairs, 3),
        rsrp=rsrp,
        beam_mask=torch.ones(pairs, beams, dtype=torch.bool),
        val_mask=torch.zeros(pairs, beams, dtype=torch.bool),
        x_scale=torch.ones(pairs),
        bound=torch.full((pairs, beams), float("nan")),
        val_pairs=torch.zeros(0, dtype=torch.long),
    )
    return pair_data, render, columns, truth, a2, cells


def fit_atoms(
    on: bool, seed: int = 0, visible: torch.Tensor | None = None, groups: int = 3, thin: int = 0
) -> tuple[PairCorrections, float]:
    """The corrections fitted with or without WNOMP's atoms (among the ``visible [2, 40]`` bins, default all;
    ``groups``: ``lambda_groups``; ``thin``: the first 24 pairs report only this many beams, 0: every beam), and
    the MAE [dB] of the corrected field through the changed antennas (never fitted) on every beam of every pair."""
    pair_data, render, columns, truth, a2, cells = atom_problem(seed)
    if thin:
        pair_data.beam_mask[:24, thin:] = False
    cfg = CorrectionsConfig(calibrate_levels=False, wnomp_atoms=on, lambda_groups=groups)
    visible = torch.ones(2, truth.shape[1], dtype=torch.bool) if visible is None else visible
    fitted = fit_corrections(cfg, pair_data, 8, np.array([7, 8]), render, columns, seed=0, visible=visible)
    field = torch.zeros_like(truth)
    bins_, x, _ = render(torch.arange(len(cells)))
    field.scatter_(1, bins_, x)
    ids = np.arange(len(cells), dtype=np.int64)
    aps = fitted.apply(field, cells.numpy(), np.array([7, 8])[cells.numpy()], ids)
    pred = torch.einsum("bmn,bn->bm", a2[cells], aps)
    true = torch.einsum("bmn,bn->bm", a2[cells], truth)
    return fitted, float((10.0 * torch.log10(pred.clamp_min(1e-12) / true)).abs().mean())


def test_wnomp_atoms_let_the_posterior_reach_a_direction_the_fields_bins_miss() -> None:
    without, err_without = fit_atoms(False)
    with_, err_with = fit_atoms(True)
    assert without.posterior is not None and with_.posterior is not None
    assert without.posterior.base is None and with_.posterior.base is not None
    assert with_.posterior.bins.shape[1] - 6 in WNOMP_ATOMS  # the field's 6 bins and the atoms chosen
    assert set(with_.posterior.atom_scores) == {0, *WNOMP_ATOMS} and not without.posterior.atom_scores
    # through the changed antenna (never fitted), the posterior with the atoms is much closer to the truth
    assert err_with < 0.5 * err_without, (err_with, err_without)
    # the held-aside score that chose λ saw the atoms too (fitted without the held-aside reports)
    assert with_.posterior.scores[with_.posterior.lam] < without.posterior.scores[without.posterior.lam] - 1.0


def test_wnomp_atoms_are_deterministic_and_survive_a_save() -> None:
    first, err = fit_atoms(True)
    again, err_again = fit_atoms(True)
    assert first.posterior is not None and again.posterior is not None and first.posterior.base is not None
    assert err == err_again and torch.equal(first.posterior.base, again.posterior.base)
    buffer = io.BytesIO()
    torch.save(first.to_state(), buffer)
    buffer.seek(0)
    loaded = PairCorrections.from_state(torch.load(buffer, weights_only=True), num_bins=40)
    aps = torch.rand(3, 40)
    args = (np.array([0, 1, 0]), np.array([7, 8, 7]), np.array([0, 1, 99]))
    torch.testing.assert_close(loaded.apply(aps, *args), first.apply(aps, *args), rtol=1e-3, atol=1e-3)
    state = first.to_state()
    state["posterior"]["base"] = -state["posterior"]["base"] - 1.0
    with pytest.raises(CheckpointError, match="pair posterior is damaged"):
        PairCorrections.from_state(state, num_bins=40)


def test_wnomp_atoms_stay_on_the_bins_a_cell_may_hold() -> None:
    visible = torch.ones(2, 40, dtype=torch.bool)
    visible[0, 6:] = False  # cell 0 holds the field's 6 bins only
    fitted, _ = fit_atoms(True, visible=visible)
    post = fitted.posterior
    assert post is not None and post.base is not None
    cell0 = torch.as_tensor(post.index.get_level_values("cell_id").to_numpy() == 7)
    assert not bool(((post.bins[cell0] >= 6) & (post.base[cell0] > 0)).any())
    assert bool(((post.bins[~cell0] >= 6) & (post.base[~cell0] > 0)).any())  # cell 1's atoms are there


def test_a_short_deadline_measures_the_levels_on_fewer_pairs_per_cell() -> None:
    """When the levels' 16 pairs per cell would take more than half of the time left, fewer per cell are rendered
    (at least one per cell), and the pass still ends by the deadline."""
    from rflscm.models.rflscm.corrections import FIRST_SHARE

    rsrp, cells, timed, now = timed_problem(400, 4, seed=2)
    rendered: list[int] = []

    def costly(pairs: torch.Tensor):
        rendered.append(pairs.numel())
        return timed(pairs)

    cfg = CorrectionsConfig(pair_posterior=False)
    args = (cfg, data(rsrp, cells), 1, np.array([7, 8, 9, 10]), costly, columns)
    cut = fit_corrections(*args, seed=0, time_left=lambda: 0.3 - now[0], clock=lambda: now[0])
    # one pair per cell first (0.04 s: 2 to warm up, 2 timed), then FIRST_SHARE of the 0.26 s left: 13 more pairs, so
    # 3 more per cell (12), 4 per cell in all
    assert rendered[:3] == [2, 2, 12] and int(FIRST_SHARE * 26) == 13
    assert cut.anchors is not None and len(cut.anchors) == 16 and now[0] <= 0.3 and cut.level_pairs == 4


def test_the_first_renders_set_up_is_not_charged_to_every_pair() -> None:
    """A model's first render sets up what later ones reuse (here 0.5 s of the fake clock once): the pass times its
    renders past ``WARM_PAIRS`` pairs, so the levels' pairs per cell follow the steady cost; timing the set-up too
    would have left one pair per cell."""
    from rflscm.models.rflscm.corrections import LEVEL_PAIRS_PER_CELL, WARM_PAIRS

    rsrp, cells, timed, now = timed_problem(400, 4, seed=2)
    rendered: list[int] = []

    def first_is_slow(pairs: torch.Tensor):
        if not rendered:
            now[0] += 0.5
        rendered.append(pairs.numel())
        return timed(pairs)

    cfg = CorrectionsConfig(pair_posterior=False)
    args = (cfg, data(rsrp, cells), 1, np.array([7, 8, 9, 10]), first_is_slow, columns)
    fitted = fit_corrections(*args, seed=0, time_left=lambda: 3.0 - now[0], clock=lambda: now[0])
    assert fitted.level_pairs == LEVEL_PAIRS_PER_CELL
    # 4 + 2.5 s left at 10 ms a pair: room for every level pair (64 = 16 per cell, 0.64 s of the 1.25 s share)
    assert rendered[:3] == [WARM_PAIRS, 4 - WARM_PAIRS, 4 * (LEVEL_PAIRS_PER_CELL - 1)]


def per_cell_cost_problem(cells: int, per_cell: int) -> tuple[PairData, Callable[..., Any], list[float]]:
    """``cells × per_cell`` pairs (sorted by cell, every beam reported at 1) and a render on a fake clock that costs
    1 ms a pair and 10 ms a cell its chunk spans: ``(pairs, render, clock)``."""
    n = cells * per_cell
    cell_of = torch.arange(n) // per_cell
    now = [0.0]

    def render(p: torch.Tensor):  # type: ignore[no-untyped-def]
        now[0] += 0.001 * p.numel() + 0.01 * cell_of[p].unique().numel()
        return torch.zeros(p.numel(), 1, dtype=torch.long), torch.ones(p.numel(), 1), torch.ones(p.numel(), 4)

    pair_data = PairData(
        cell_index=cell_of,
        grid_ids=np.arange(n, dtype=np.int64),
        grid_xyz=torch.zeros(n, 3),
        rsrp=torch.ones(n, 4),
        beam_mask=torch.ones(n, 4, dtype=torch.bool),
        val_mask=torch.zeros(n, 4, dtype=torch.bool),
        x_scale=torch.ones(n),
        bound=torch.full((n, 4), float("nan")),
        val_pairs=torch.zeros(0, dtype=torch.long),
    )
    return pair_data, render, now


def test_the_later_pairs_come_in_random_blocks_each_sorted_and_the_estimate_times_such_a_chunk() -> None:
    """The pass takes the pairs it has not rendered in a seeded random order of ``PASS_BLOCK``-pair blocks, each sorted
    (so a render chunk spans few cells); ``measure_pass`` times its per-pair render on a chunk of such a block, not on
    pairs spread over every cell: with a render that costs per pair and per cell in the chunk, the estimate is the
    block chunk's cost."""
    import rflscm.models.rflscm.corrections as module

    cells, per_cell = 40, 100
    n = cells * per_cell
    pairs = torch.arange(n)
    first = torch.arange(0, n, 7)
    order = module._later_pairs(pairs, first, seed=3)
    rest = pairs[~torch.isin(pairs, first)]
    assert torch.equal(order.sort().values, rest)  # every pair not rendered first, once
    blocks = order.split(module.PASS_BLOCK)
    assert all(torch.equal(b, b.sort().values) for b in blocks)
    assert int(blocks[0].max() - blocks[0].min()) > n // 2  # a block is drawn over the whole network
    assert torch.equal(order, module._later_pairs(pairs, first, seed=3))
    assert not torch.equal(order, module._later_pairs(pairs, first, seed=4))

    pair_data, render, now = per_cell_cost_problem(cells, per_cell)
    cell_of = pair_data.cell_index
    cfg = CorrectionsConfig(pair_posterior=False, wnomp_fallback=False)
    times = module.measure_pass(cfg, pair_data, 2, cells, render, columns, lambda: now[0])
    block_cells = int(cell_of[module._later_pairs(pairs, pairs[:0], 0)[: module.PASS_BLOCK]].unique().numel())
    assert block_cells == cells  # a block covers the network; a chunk of it spans few cells
    assert times.render_s < 0.001 + 0.01 * 4 / module.PAIR_CHUNK  # at most four cells in the chunk
    spread = 0.001 + 0.01 * cells / module.PAIR_CHUNK  # what a chunk spread over every cell costs a pair
    assert times.render_s < 0.5 * spread


def test_the_first_pairs_are_priced_by_the_cells_their_chunks_span() -> None:
    """A render costs per pair and per cell its chunk spans. The first pairs (one per cell) pay a cell per pair, a
    block's chunk (``known``) a few: from the two the pass prices the levels' further pairs (sorted, so a cell's pairs
    share chunks) at what their chunks span. Priced at the first pairs' cost it would take 3 pairs per cell; so priced
    it takes all 16 within its share of the time left, and ends by the deadline."""
    import rflscm.models.rflscm.corrections as module

    cells = 40
    pair_data, render, now = per_cell_cost_problem(cells, 100)
    cfg = CorrectionsConfig(pair_posterior=False, wnomp_fallback=False)
    known = module.measure_pass(cfg, pair_data, 2, cells, render, columns, lambda: now[0])
    assert known.cells_per_pair <= 4 / module.PAIR_CHUNK  # a chunk of a block spans a few cells

    def level_pairs(times: module.PassTimes | None) -> tuple[int, float]:
        now[0] = 0.0
        args = (cfg, pair_data, 2, np.arange(cells), render, columns)
        fitted = fit_corrections(*args, seed=0, time_left=lambda: 2.8 - now[0], clock=lambda: now[0], known=times)
        return fitted.level_pairs, now[0]

    # one pair per cell: 38 timed in one chunk of 38 cells, 11 ms a pair; 15 more per cell (600 pairs in 10 chunks of
    # about 5 cells each) cost about 1.1 s, within half of the 2.4 s left, where 11 ms a pair would price them 6.6 s
    assert level_pairs(None)[0] == 3
    taken, ended = level_pairs(known)
    assert taken == module.LEVEL_PAIRS_PER_CELL and ended <= 2.8


def test_wnomp_fallback_solves_chunks_of_consecutive_pairs_and_the_estimate_times_such_a_chunk(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """WNOMP's solve pays per cell of a chunk: the fallback solves the pairs it is given (in the pass's random block
    order) sorted, in chunks of consecutive pairs (a few cells each) drawn in a seeded random order, and returns them
    in pair order; ``measure_pass`` times its per-pair solve on such a chunk, not on pairs spread over every cell."""
    import rflscm.models.rflscm.corrections as module

    cells, per_cell = 40, 300
    n = cells * per_cell
    pairs = torch.arange(n)
    cell_of = pairs // per_cell
    now, seen = [0.0], []

    def solve(self, p: torch.Tensor, mask: torch.Tensor, levels: object, solver: object = None):
        seen.append(p.clone())
        now[0] += 1e-4 * p.numel() + 0.02 * cell_of[p].unique().numel()  # per pair, and per cell in the chunk
        return torch.full((p.numel(), 2), -1), torch.zeros(p.numel(), 2)

    def render(p: torch.Tensor):
        return torch.zeros(p.numel(), 1, dtype=torch.long), torch.ones(p.numel(), 1), torch.ones(p.numel(), 4)

    monkeypatch.setattr(module._Fit, "solve", solve)
    pair_data = PairData(
        cell_index=cell_of, grid_ids=np.arange(n, dtype=np.int64), grid_xyz=torch.zeros(n, 3),
        rsrp=torch.ones(n, 4), beam_mask=torch.ones(n, 4, dtype=torch.bool), val_mask=torch.zeros(n, 4, dtype=torch.bool),
        x_scale=torch.ones(n), bound=torch.full((n, 4), float("nan")), val_pairs=torch.zeros(0, dtype=torch.long),
    )  # fmt: skip
    cfg = CorrectionsConfig(pair_posterior=False)
    fit = module._Fit(cfg, pair_data, 2, cells, render, columns, torch.ones(cells, 4, dtype=torch.bool))
    later = module._later_pairs(pairs, pairs[:0], 0)
    fb = fit.fallback(later, np.arange(cells) + 100, None, {}, lambda: 1e9, lambda: now[0])
    assert list(fb.index.get_level_values("grid_id")) == list(range(n))  # every pair once, in pair order
    span = -(-module.FALLBACK_SOLVE // per_cell) + 1
    assert len(seen) == -(-n // module.FALLBACK_SOLVE)
    assert all(int(cell_of[p].unique().numel()) <= span and torch.equal(p, p.sort().values) for p in seen)
    starts = [int(p[0]) for p in seen]
    assert starts != sorted(starts)  # chunks drawn over the network
    assert now[0] < 1e-4 * n + 0.02 * (cells + len(seen))  # about once per cell, not once per cell and chunk
    now[0], seen[:] = 0.0, []
    times = module.measure_pass(cfg, pair_data, 2, cells, render, columns, lambda: now[0])
    assert times.solve_s < 1e-4 + 0.02 * span / module.FALLBACK_CHUNK
    assert times.solve_s < 0.5 * (1e-4 + 0.02 * cells / module.FALLBACK_CHUNK)  # a chunk spread over every cell


def fallback_problem(pairs: int = 400):
    """:func:`atom_problem` with many pairs and a clock that charges 10 ms per rendered pair."""
    pair_data, render_, columns_, truth, a2, cells = atom_problem(0, pairs=pairs)
    now = [0.0]

    def costly(p: torch.Tensor):
        now[0] += 0.01 * p.numel()
        return render_(p)

    return pair_data, costly, columns_, truth, a2, cells, now


def test_pairs_the_pass_cannot_reach_get_wnomps_aps_when_it_predicts_held_reports_better() -> None:
    """Within a deadline the pairs left over get WNOMP's sparse APS of their own reports (the field misses their
    atom, so WNOMP wins the held-aside choice); the corrected and the WNOMP pairs are disjoint and cover every pair;
    such a pair's APS is WNOMP's whole, which predicts the changed antennas better than the field with its level;
    without the switch they keep the level; and it survives a save."""
    pair_data, costly, columns_, truth, a2, cells, now = fallback_problem()
    visible = torch.ones(2, truth.shape[1], dtype=torch.bool)
    ids = np.array([7, 8])

    def run(on: bool) -> PairCorrections:
        now[0] = 0.0
        cfg = CorrectionsConfig(pair_posterior=False, wnomp_fallback=on)
        return fit_corrections(
            cfg, pair_data, 8, ids, costly, columns_, 0, time_left=lambda: 2.0 - now[0], clock=lambda: now[0],
            visible=visible,
        )  # fmt: skip

    with_wnomp, level_only = run(True), run(False)
    assert level_only.fallback is None
    fb = with_wnomp.fallback
    assert fb is not None and fb.scores["wnomp"] < fb.scores["level"]
    assert with_wnomp.anchors is not None and len(fb.index) > 0
    assert not set(fb.index) & set(with_wnomp.anchors.index)
    assert len(fb.index) + len(with_wnomp.anchors) == len(cells)
    rows = np.array([g for _, g in fb.index])
    field = torch.full((len(rows), truth.shape[1]), 0.1)
    c = cells.numpy()[rows]
    out = with_wnomp.apply(field, c, ids[c], rows)
    assert with_wnomp.unrendered(ids[c], rows).all()
    dense = torch.zeros_like(out).scatter_add_(1, fb.bins.clamp_min(0), torch.where(fb.bins >= 0, fb.gains, 0.0))
    torch.testing.assert_close(out, dense)

    def mae(aps: torch.Tensor) -> float:
        pred = torch.einsum("bmn,bn->bm", a2[cells[rows]], aps)
        true = torch.einsum("bmn,bn->bm", a2[cells[rows]], truth[rows])
        return float((10.0 * torch.log10(pred.clamp_min(1e-12) / true)).abs().mean())

    assert mae(out) < mae(level_only.apply(field, c, ids[c], rows))
    buffer = io.BytesIO()
    torch.save(with_wnomp.to_state(), buffer)
    buffer.seek(0)
    loaded = PairCorrections.from_state(torch.load(buffer, weights_only=True), truth.shape[1])
    torch.testing.assert_close(loaded.apply(field, c, ids[c], rows), out)


def test_where_the_budget_cannot_render_the_pairs_left_wnomps_aps_answers_them_though_the_field_predicts_better() -> (
    None
):
    """The field here is the truth, so the held-aside choice keeps its level for the pairs the pass leaves, which the
    pass then renders (``render_rest``). Where the time left cannot render them all, the better render-free answer takes
    them (here WNOMP's APS; the budget's choice, ``scores["budget"]``), and the pass corrects what it can; where it can
    render them all, none; without ``render_rest`` the choice is the held-aside one whatever the time."""
    pair_data, _, columns_, truth, _, cells, now = fallback_problem()

    def exact(p: torch.Tensor):  # the true APS, 10 ms a pair
        now[0] += 0.01 * p.numel()
        bins = torch.arange(truth.shape[1]).expand(len(p), -1)
        return bins, truth[p], torch.einsum("bmk,bk->bm", columns_(cells[p], bins), truth[p])

    visible = torch.ones(2, truth.shape[1], dtype=torch.bool)

    def run(deadline: float, rest: bool = True) -> PairCorrections:
        now[0] = 0.0
        return fit_corrections(
            CorrectionsConfig(pair_posterior=False), pair_data, 8, np.array([7, 8]), exact, columns_, 0,
            time_left=lambda: deadline - now[0], clock=lambda: now[0], visible=visible, render_rest=rest,
        )  # fmt: skip

    ample, short, alone, some = run(6.0), run(2.0), run(2.0, rest=False), run(4.0)
    assert ample.fallback is not None and not len(ample.fallback.index) and "budget" not in ample.fallback.scores
    assert ample.fallback.scores["level"] < ample.fallback.scores["wnomp"]
    assert ample.rendered is not None and len(ample.rendered.index) == len(cells)
    fb = short.fallback
    assert fb is not None and fb.scores["budget"] == 1.0 and fb.scores["level"] < fb.scores["wnomp"]
    assert short.anchors is not None and len(fb.index) + len(short.anchors) == len(cells)
    assert not set(fb.index) & set(short.anchors.index)
    assert alone.fallback is not None and not len(alone.fallback.index)
    # with more time the pass corrects more of them itself: fewer left for WNOMP's APS
    assert some.fallback is not None and some.fallback.scores["budget"] == 1.0 and some.rendered is not None
    assert 0 < len(some.fallback.index) < len(fb.index)
    assert len(some.fallback.index) + len(some.rendered.index) == len(cells)


def test_the_left_over_pairs_are_solved_with_the_wnomp_settings_the_config_gives() -> None:
    """``wnomp_fallback`` as WNOMP settings (the demo's selected baseline): the left-over pairs' APS is WNOMP's
    solution of their reports with exactly those settings (2 atoms here), where True gives the defaults' 8."""
    from rflscm.models.rflscm.fallback import SOLVER, solve_reports
    from rflscm.models.wnomp import WNOMPConfig

    pair_data, costly, columns_, truth, _, cells, now = fallback_problem()
    visible = torch.ones(2, truth.shape[1], dtype=torch.bool)
    two = WNOMPConfig(k_max=2, tolerance=0.05, residual_floor=0.25)

    def run(setting: bool | WNOMPConfig) -> PairCorrections:
        now[0] = 0.0
        cfg = CorrectionsConfig(pair_posterior=False, wnomp_fallback=setting)
        return fit_corrections(
            cfg, pair_data, 8, np.array([7, 8]), costly, columns_, 0, time_left=lambda: 2.0 - now[0],
            clock=lambda: now[0], visible=visible,
        )  # fmt: skip

    default, selected = run(True).fallback, run(two).fallback
    assert default is not None and selected is not None and len(selected.index) > 0
    assert default.bins.shape[1] == SOLVER.k_max == 8 and selected.bins.shape[1] == 2
    rows = torch.as_tensor([g for _, g in selected.index])  # this problem's grid id is its pair's index
    every = torch.arange(truth.shape[1])[None]

    def matrix(cell: int) -> torch.Tensor:
        return columns_(torch.tensor([cell]), every)[0]

    bins, gains = solve_reports(matrix, cells[rows], pair_data.rsrp[rows], pair_data.observed[rows], two)
    assert torch.equal(selected.bins, bins)
    torch.testing.assert_close(selected.gains, gains)


def test_damaged_wnomp_pairs_are_refused_in_one_line() -> None:
    from rflscm.models.rflscm.fallback import PairFallback

    good = PairFallback(
        pd.MultiIndex.from_arrays([np.array([1]), np.array([2])]), torch.tensor([[0, -1]]), torch.tensor([[1.0, 0.0]])
    ).to_state()
    assert PairFallback.from_state(good, 4) is not None
    for key, value, why in (
        ("gains", torch.tensor([[-1.0, 0.0]]), "negative"),
        ("bins", torch.tensor([[9, -1]]), "off the angle grid"),
        ("bins", torch.tensor([[0]]), "shapes"),
    ):
        with pytest.raises(CheckpointError, match=why):
            PairFallback.from_state({**good, key: value}, 4)
    with pytest.raises(CheckpointError, match="expected"):
        PairFallback.from_state({"cell_id": 1}, 4)


def test_pairs_with_few_and_many_reports_choose_their_posterior_apart() -> None:
    grouped, _ = fit_atoms(True, groups=2, thin=3)
    post = grouped.posterior
    assert post is not None and post.base is not None
    assert [g["min_reports"] for g in post.groups] == [3.0, 16.0] and sum(g["pairs"] for g in post.groups) == 48
    few = torch.as_tensor(post.index.get_level_values("grid_id").to_numpy() < 24)
    for group, rows in zip(post.groups, (few, ~few), strict=True):
        atoms = (post.bins[rows] != post.bins[rows][:, :1]).sum(1).max()  # columns beyond the field's 6 bins
        if math.isinf(group["lam"]):  # the field kept: no gain, no atom
            assert float(post.gain_db[rows].abs().max()) == 0.0 and float(post.base[rows].max()) == 0.0
        else:
            assert int(atoms) <= 6 + group["atoms"]
    # the many-report pairs follow their reports to the atom; one choice for all does not do better on them
    assert post.groups[1]["atoms"] > 0 and math.isfinite(post.groups[1]["lam"])
    pooled, _ = fit_atoms(True, groups=1, thin=3)
    assert pooled.posterior is not None and len(pooled.posterior.groups) == 1
    assert pooled.posterior.groups[0]["lam"] == pooled.posterior.lam


def test_chunks_whose_groups_take_different_atom_counts_stack_into_one_posterior(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A chunk holds the field's bins and the most WNOMP atoms of its pairs' groups, so chunks of one group each
    differ in width (a 222-cell field run in tiles raised "Sizes of tensors must match" when the pass took its pairs
    sorted by cell); the posterior stacks them widened with no-op columns, and predicts as with one chunk for all."""
    import rflscm.models.rflscm.corrections as module

    whole, _ = fit_atoms(True, groups=2, thin=3)  # 48 pairs in one chunk
    monkeypatch.setattr(module, "PAIR_CHUNK", 24)  # the 24 few-report pairs, then the 24 others
    split, _ = fit_atoms(True, groups=2, thin=3)
    post, post_split = whole.posterior, split.posterior
    assert post is not None and post_split is not None
    assert post.groups[0]["atoms"] != post.groups[1]["atoms"] or math.isinf(post.groups[0]["lam"])
    field = torch.rand(48, 40, generator=torch.Generator().manual_seed(1))
    cells = (torch.arange(48) % 2).numpy()
    ids = np.array([7, 8])[cells]
    grids = np.arange(48, dtype=np.int64)
    torch.testing.assert_close(post_split.apply(field, ids, grids), post.apply(field, ids, grids))


def test_widening_a_posteriors_blocks_changes_nothing_it_predicts() -> None:
    """The added columns repeat a row's first bin with a gain of 0 dB and a base of 0."""
    from rflscm.models.rflscm.corrections import _widened

    index = pd.MultiIndex.from_arrays([np.array([7, 7, 8]), np.array([0, 1, 2])], names=["cell_id", "grid_id"])
    bins = [torch.tensor([[3, 5]]), torch.tensor([[1, 2, 4], [0, 6, 7]])]
    gains = [torch.tensor([[1.0, -2.0]]), torch.tensor([[0.5, 0.0, 3.0], [-1.0, 2.0, 0.0]])]
    bases = [torch.tensor([[0.0, 0.1]]), torch.tensor([[0.2, 0.0, 0.0], [0.0, 0.3, 0.1]])]
    wide = PairPosterior(index, _widened(bins), _widened(gains), 1.0, {}, _widened(bases))
    assert wide.bins.shape == (3, 3) and wide.bins[0].tolist() == [3, 5, 3] and wide.gain_db[0, 2] == 0.0
    aps = torch.rand(3, 8, generator=torch.Generator().manual_seed(0))
    first = PairPosterior(index[:1], bins[0], gains[0], 1.0, {}, bases[0])
    out = wide.apply(aps, np.array([7, 7, 8]), np.array([0, 1, 2]))
    torch.testing.assert_close(out[:1], first.apply(aps[:1], np.array([7]), np.array([0])))


def test_the_mixed_prior_lowers_the_field_through_the_anchor_and_adds_wnomps_atoms() -> None:
    from rflscm.models.rflscm.corrections import _Fit, _Plan
    from rflscm.models.rflscm.posterior import WNOMP_PRIORS

    pair_data, render, columns, truth, _, _ = atom_problem(0)
    mix = next(i for i, (_, field_db) in enumerate(WNOMP_PRIORS) if field_db > 0)
    cfg = CorrectionsConfig(calibrate_levels=False)
    fit = _Fit(cfg, pair_data, 8, 2, render, columns, torch.ones(2, truth.shape[1], dtype=torch.bool))
    rendered = fit.render_pairs(torch.arange(16), top=True)
    rows = torch.arange(16)
    fit.plan = _Plan.uniform(0, 0, 0.3)
    (field,) = fit.chunks(rendered, rows, None)
    fit.plan = _Plan.uniform(2, mix, 0.3)
    (mixed,) = fit.chunks(rendered, rows, None)
    lower = WNOMP_PRIORS[mix][1]
    torch.testing.assert_close(mixed.anchor, field.anchor - lower)  # every bin of the field, in every round
    torch.testing.assert_close(mixed.top_x[:, :6], field.top_x * 10 ** (-lower / 10))
    assert mixed.base is not None and float(mixed.base[:, 6].min()) > 0.0  # WNOMP's first atom, off the field's bins
    # the prior's prediction: the field's share plus the atoms'; the residuals are against it
    cols, centre, rest = mixed.fit_inputs()
    prior = torch.einsum("bmn,bn->bm", cols, centre) + rest
    share = (torch.einsum("bmn,bn->bm", field.cols, field.top_x) + field.rest) * 10 ** (-lower / 10)
    assert bool((prior >= share * (1 - 1e-5)).all()) and bool((prior > share * 1.01).any())
    torch.testing.assert_close(mixed.resid, field.resid + lower - 10 * torch.log10(prior / share), atol=1e-4, rtol=0)


def test_wnomps_aps_of_the_left_over_pairs_is_solved_only_while_it_fits(monkeypatch: pytest.MonkeyPatch) -> None:
    """Within a budget the left-over pairs' WNOMP solutions come a chunk at a time while one fits: a chunk that costs
    more than the time left is not started, and those pairs keep the field's level (a tile of 53 k pairs spent 39 s
    of its pass on them; a loaded machine would overrun)."""
    import rflscm.models.rflscm.corrections as module

    pair_data, costly, columns_, truth, _, cells, now = fallback_problem(pairs=400)
    visible = torch.ones(2, truth.shape[1], dtype=torch.bool)
    solve = module._Fit.solve

    def slow_solve(self, pairs, mask, levels, solver=module.SOLVER):  # type: ignore[no-untyped-def]
        now[0] += 0.01 * pairs.numel()  # 10 ms a pair: a chunk of 32 costs 0.32 s
        return solve(self, pairs, mask, levels, solver)

    monkeypatch.setattr(module._Fit, "solve", slow_solve)
    monkeypatch.setattr(module, "FALLBACK_SOLVE", 32)
    monkeypatch.setattr(module, "FALLBACK_CHUNK", 16)  # the pass times its solve on this many pairs (0.16 s here)

    def run(seconds: float) -> PairCorrections:
        now[0] = 0.0
        cfg = CorrectionsConfig(pair_posterior=False)
        return fit_corrections(
            cfg, pair_data, 8, np.array([7, 8]), costly, columns_, 0, time_left=lambda: seconds - now[0],
            clock=lambda: now[0], visible=visible,
        )  # fmt: skip

    short = run(2.5)
    assert short.fallback is not None and short.anchors is not None
    assert now[0] <= 2.5  # the pass ends by its deadline
    assert len(short.fallback.index) > 0
    assert len(short.fallback.index) + len(short.anchors) < len(cells)  # the rest keep the field's level
    grids = [g for _, g in short.fallback.index]  # this problem's grid id is its pair's index
    assert grids == sorted(grids)  # stored in pair order
    monkeypatch.setattr(module, "FALLBACK_SOLVE", 10**6)  # every left-over pair in one solve: past the deadline
    run(2.5)
    assert now[0] > 2.5


def test_posterior_pairs_get_wnomps_aps_of_their_reports_for_the_db_mix(monkeypatch: pytest.MonkeyPatch) -> None:
    """Where a group chose a posterior (finite λ) and its held-aside reports chose a weight > 0, each of its pairs
    gets WNOMP's APS of all its reports (atoms chosen on held-aside reports among ``MIX_ATOMS``) with its group's
    weight; a pair of a group that kept the field gets none; no mix when 0 is the only weight or without WNOMP's
    atoms; deterministic; it survives a save, and damaged weights are refused in one line."""
    from rflscm.models.rflscm import corrections as module

    fitted, _ = fit_atoms(True)
    post, mix = fitted.posterior, fitted.mix
    assert post is not None and mix is not None and mix.weight is not None
    assert {f"k{k}" for k in module.MIX_ATOMS} <= set(mix.scores)
    chosen = min(module.MIX_ATOMS, key=lambda k: (mix.scores[f"k{k}"], k))
    assert int((mix.bins >= 0).sum(1).max()) <= chosen  # at most the chosen count of atoms per pair
    weights = {mix.scores[k] for k in mix.scores if k.startswith("w")}
    assert set(mix.weight.tolist()) <= weights - {0.0} and set(mix.weight.tolist()) <= set(module.MIX_WEIGHTS)
    assert set(mix.index) <= set(post.index) and len(mix.index) > 0
    again, _ = fit_atoms(True)
    assert again.mix is not None and torch.equal(again.mix.bins, mix.bins) and torch.equal(again.mix.gains, mix.gains)
    buffer = io.BytesIO()
    torch.save(fitted.to_state(), buffer)
    buffer.seek(0)
    loaded = PairCorrections.from_state(torch.load(buffer, weights_only=True), num_bins=40)
    assert loaded.mix is not None and loaded.mix.weight is not None and torch.equal(loaded.mix.weight, mix.weight)
    assert list(loaded.mix.index) == list(mix.index) and torch.equal(loaded.mix.bins.long(), mix.bins.long())
    for bad in (mix.weight * 0 + 1.5, mix.weight[:-1], None):
        state = fitted.to_state()
        if bad is None:
            del state["mix"]["weight"]
        else:
            state["mix"]["weight"] = bad
        with pytest.raises(
            CheckpointError, match=r"^the checkpoint's (pair corrections are|dB mix of WNOMP's APS is) dam"
        ):
            PairCorrections.from_state(state, num_bins=40)
    without_atoms, _ = fit_atoms(False)
    assert without_atoms.mix is None
    monkeypatch.setattr(module, "MIX_WEIGHTS", (0.0,))
    off, _ = fit_atoms(True)
    assert off.mix is None and off.posterior is not None


def test_each_beam_type_has_its_own_mix_chosen_on_its_own_held_aside_reports(monkeypatch: pytest.MonkeyPatch) -> None:
    """The mix is chosen per beam type (``MIX_BEAM_TYPES``): SSB's on its held-aside SSB reports, CSI-RS's on its
    CSI-RS ones (the atom count with the least error of each, scored on that type alone); ``mix_for`` hands each beam
    type its own, a checkpoint keeps both, and one written before (a single ``mix``) serves both beam types with it."""
    from rflscm.models.rflscm import corrections as module

    fitted, _ = fit_atoms(True)
    ssb, csi = fitted.mix_for("ssb"), fitted.mix_for("csi")
    assert ssb is fitted.mix and csi is fitted.mix_csi and ssb is not None and csi is not None
    assert ssb.scores != csi.scores  # each scored on its own reports
    for mix in (ssb, csi):
        chosen = min(module.MIX_ATOMS, key=lambda k: (mix.scores[f"k{k}"], k))
        assert int((mix.bins >= 0).sum(1).max()) <= chosen
    buffer = io.BytesIO()
    torch.save(fitted.to_state(), buffer)
    buffer.seek(0)
    loaded = PairCorrections.from_state(torch.load(buffer, weights_only=True), num_bins=40)
    assert loaded.mix_csi is not None and torch.equal(loaded.mix_csi.gains, csi.gains)
    state = fitted.to_state()
    del state["mix_csi"]
    old = PairCorrections.from_state(state, num_bins=40)
    assert old.mix_csi is None and old.mix_for("csi") is old.mix and old.mix is not None
    # a beam type whose reports chose no mix keeps its posterior unmixed, though the other's chose one
    monkeypatch.setattr(module, "MIX_BEAM_TYPES", ("ssb",))
    ssb_only, _ = fit_atoms(True)
    assert ssb_only.mix is not None and len(ssb_only.mix.index) > 0
    none = ssb_only.mix_for("csi")
    assert none is not None and len(none.index) == 0 and (none.rows(np.array([7]), np.array([0])) < 0).all()
    buffer = io.BytesIO()
    torch.save(ssb_only.to_state(), buffer)
    buffer.seek(0)
    again = PairCorrections.from_state(torch.load(buffer, weights_only=True), num_bins=40).mix_for("csi")
    assert again is not None and len(again.index) == 0


def test_beam_types_that_choose_the_same_atoms_share_one_solve_and_keep_their_own_weights(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With one atom count to choose from, both beam types' mixes come from a single WNOMP solve of their pairs, each
    restricted to its own pairs, with its own weights and scores (not one shared object)."""
    from rflscm.models.rflscm import corrections as module

    calls: list[int] = []
    fallback = module._Fit.fallback

    def spy(self, pairs, *args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(int(pairs.numel()))
        return fallback(self, pairs, *args, **kwargs)

    monkeypatch.setattr(module, "MIX_ATOMS", (4,))
    monkeypatch.setattr(module._Fit, "fallback", spy)
    fitted, _ = fit_atoms(True)
    ssb, csi = fitted.mix_for("ssb"), fitted.mix_for("csi")
    assert ssb is not None and csi is not None and len(ssb.index) and len(csi.index)
    assert len(calls) == 1 and calls[0] == len(set(ssb.index) | set(csi.index))  # no left-over pairs: no budget
    assert ssb is not csi and ssb.weight is not csi.weight and ssb.scores is not csi.scores
    common = sorted(set(ssb.index) & set(csi.index))
    at_s, at_c = ssb.index.get_indexer(common), csi.index.get_indexer(common)
    assert torch.equal(ssb.bins[at_s], csi.bins[at_c]) and torch.equal(ssb.gains[at_s], csi.gains[at_c])


def test_the_mix_weight_follows_which_of_the_two_predicts_held_aside_reports_better() -> None:
    """A dB average's error is the same average of the two errors: with WNOMP's held-aside errors zero the largest
    weight wins, with them far larger than the posterior's none does (the choice reads the errors, nothing else)."""
    from rflscm.models.rflscm import corrections as module

    e_post = torch.tensor([2.0, -3.0, 1.0, 4.0], dtype=torch.float64)
    for e_wnomp, expected in ((torch.zeros(4, dtype=torch.float64), 1.0), (e_post * 0 + 15.0, 0.0)):
        err = {
            w: float(((1 - w) * e_post + w * e_wnomp).abs().clamp_max(module.CLIP_DB).mean())
            for w in module.MIX_WEIGHTS
        }
        assert min(module.MIX_WEIGHTS, key=lambda w: (err[w], w)) == expected


def test_a_checkpoint_written_before_the_mix_loads_without_one() -> None:
    fitted, _ = fit_atoms(True)
    state = fitted.to_state()
    del state["mix"]
    loaded = PairCorrections.from_state(state, num_bins=40)
    assert loaded.mix is None


def test_round_one_silence_caps_only_unreported_pairs_at_visited_grids_and_survives_a_save() -> None:
    from rflscm.models.rflscm.corrections import RoundOneCensor

    reported = pd.MultiIndex.from_arrays([np.array([7, 7, 8]), np.array([100, 101, 100])], names=["cell_id", "grid_id"])
    censor = RoundOneCensor(reported, np.array([100, 101]), -120.0)
    caps = censor.caps_mw(np.array([7, 8, 8, 7]), np.array([100, 101, 102, 101]))
    # reported; silent at a visited grid (capped at -120 dBm); a grid round 1 never visited; reported
    assert np.isnan(caps[0]) and caps[1] == pytest.approx(1e-12) and np.isnan(caps[2]) and np.isnan(caps[3])
    buffer = io.BytesIO()
    torch.save(PairCorrections(censor=censor).to_state(), buffer)
    buffer.seek(0)
    loaded = PairCorrections.from_state(torch.load(buffer, weights_only=True), num_bins=4).censor
    assert loaded is not None and loaded.cap_dbm == -120.0 and list(loaded.reported) == list(reported)
    assert np.array_equal(loaded.visited, [100, 101])
    for key, bad in (("cap_dbm", torch.tensor(float("nan"))), ("grid_id", torch.tensor([1.5])), ("visited", None)):
        state = PairCorrections(censor=censor).to_state()
        state["censor"][key] = bad
        with pytest.raises(CheckpointError, match=r"^the checkpoint's round-1 silence table is damaged \("):
            PairCorrections.from_state(state, num_bins=4)
    assert PairCorrections.from_state({"censor": None}, num_bins=4).censor is None  # a checkpoint from before it


def test_a_mix_cut_short_takes_the_missing_pairs_from_the_left_over_solutions() -> None:
    """When the mix's own WNOMP solve is cut by the time left, the corrected pairs it missed take WNOMP's APS solved
    for them before the pass reached them (padded to one width), so every corrected pair of a mixing group is mixed;
    a pair neither has stays out, and without left-over solutions the mix is unchanged."""
    from rflscm.models.rflscm.corrections import _with_solved
    from rflscm.models.rflscm.fallback import PairFallback

    def index(grids: list[int]) -> pd.MultiIndex:
        return pd.MultiIndex.from_arrays([[7] * len(grids), grids], names=["cell_id", "grid_id"])

    mix = PairFallback(
        index([1, 2]), torch.tensor([[3, -1], [4, 5]]), torch.tensor([[1.0, 0.0], [2.0, 3.0]]), {"k2": 1}
    )
    solved = PairFallback(
        index([2, 3, 4, 5]), torch.tensor([[0, 1, 2]] * 4), torch.arange(12, dtype=torch.float32).reshape(4, 3)
    )
    out = _with_solved(mix, solved, pd.MultiIndex.from_arrays([[7, 7, 7, 7], [1, 2, 3, 9]]))
    assert list(out.index) == [(7, 1), (7, 2), (7, 3)] and out.scores == {"k2": 1}
    torch.testing.assert_close(out.bins, torch.tensor([[3, -1, -1], [4, 5, -1], [0, 1, 2]]))
    torch.testing.assert_close(out.gains, torch.tensor([[1.0, 0.0, 0.0], [2.0, 3.0, 0.0], [3.0, 4.0, 5.0]]))
    aps = out.apply(torch.zeros(1, 8), np.array([7]), np.array([3]))
    torch.testing.assert_close(aps, torch.tensor([[3.0, 4.0, 5.0, 0, 0, 0, 0, 0]]))
    assert _with_solved(mix, None, index([1, 2, 3])) is mix
    assert _with_solved(mix, solved, index([1, 2])) is mix


@pytest.mark.parametrize(("posterior", "wide_later"), [(False, False), (True, False), (False, True)])
def test_pairs_left_over_borrow_the_nearest_rendered_pairs_aps_with_their_own_anchor_where_that_predicts_best(
    posterior: bool, wide_later: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each cell's pairs share one angular shape and differ in level; the field renders that shape at a wrong level per
    pair. The held-aside choice for the pairs the pass leaves then prefers the nearest rendered pair's APS with the
    pair's own anchor (the shape is right, the reports pin the level) over the field's level and over WNOMP; such a
    pair's corrected APS is its neighbour's kept render with its own anchor, no render of its own, and predicts a
    changed antenna nearly as the truth does; the train line's count says so. With the posterior, its gains belong
    to the corrected pairs only (a borrowed pair has an anchor, no gains), and every pair's APS applies. Where the
    pass's later renders are too wide to keep, the pairs left have nothing to borrow and get WNOMP's APS after all:
    none is left for the caller to render."""
    gen = torch.Generator().manual_seed(3)
    pairs, beams, bins = 400, 12, 30
    a = torch.rand(2, beams, bins, generator=gen) ** 3
    a2 = torch.rand(2, beams, bins, generator=gen) ** 3  # the changed antennas'
    cells = torch.arange(pairs) % 2
    shape = torch.rand(2, bins, generator=gen) ** 4
    level = 10 ** (torch.randn(pairs, generator=gen) / 10 * 8)  # ±8 dB between pairs
    truth = shape[cells] * level[:, None]
    field = shape[cells] * 10 ** (torch.randn(pairs, generator=gen) / 10 * 6)[:, None]  # the wrong level per pair
    if posterior:  # each pair's own shape differs a little from its cell's: its reports have something to fit
        truth = truth * 10 ** (torch.randn(pairs, bins, generator=torch.Generator().manual_seed(4)) / 10 * 1.5)
    now = [0.0]
    calls = [0]
    monkeypatch.setattr(corrections_module, "KEPT_BINS", bins)

    def render(p: torch.Tensor):
        now[0] += 0.01 * p.numel()
        calls[0] += 1
        b, x = torch.arange(bins).expand(len(p), bins), field[p]
        # past the first pairs' renders (the warm-up, one pair per cell, the levels' and λ's others): the same APS
        # with empty bins beyond, wider than the pass keeps
        if wide_later and calls[0] > 3:
            b, x = torch.cat([b, b[:, :4]], 1), torch.cat([x, torch.zeros(len(p), 4)], 1)
        return b, x, torch.einsum("bmk,bk->bm", a[cells[p]], field[p])

    def columns(c: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return torch.gather(a[c], 2, b[:, None, :].expand(-1, beams, -1))

    xyz = torch.zeros(pairs, 3)
    xyz[:, 0] = torch.arange(pairs, dtype=torch.float32) * 5.0  # a street: neighbours 10 m apart within a cell
    data_ = PairData(
        cell_index=cells, grid_ids=np.arange(pairs, dtype=np.int64), grid_xyz=xyz,
        rsrp=torch.einsum("bmn,bn->bm", a[cells], truth), beam_mask=torch.ones(pairs, beams, dtype=torch.bool),
        val_mask=torch.zeros(pairs, beams, dtype=torch.bool), x_scale=torch.ones(pairs),
        bound=torch.full((pairs, beams), float("nan")), val_pairs=torch.zeros(0, dtype=torch.long),
    )  # fmt: skip
    ids = np.array([7, 8])
    fitted = fit_corrections(
        CorrectionsConfig(pair_posterior=posterior, wnomp_atoms=False), data_, 6, ids, render, columns, 0,
        time_left=lambda: 2.0 - now[0], clock=lambda: now[0], visible=torch.ones(2, bins, dtype=torch.bool),
    )  # fmt: skip
    if posterior:
        assert fitted.posterior is not None and fitted.anchors is not None
        assert len(fitted.posterior.index) == fitted.posterior.bins.shape[0] == fitted.corrected_pairs()
        assert not fitted.posterior.index.isin(fitted.anchors.index[int(fitted.corrected_pairs()) :]).any()
        every = np.arange(pairs)
        assert torch.isfinite(fitted.apply(field.clone(), cells.numpy(), ids[cells.numpy()], every)).all()
    fb = fitted.fallback
    assert fb is not None
    if wide_later:  # no render kept beyond the first chunks, so none to borrow: WNOMP answers every pair left
        assert fitted.borrowed == 0 and fb.scores["borrow"] < min(fb.scores["level"], fb.scores["wnomp"])
        assert 0 < fitted.corrected_pairs() < pairs and len(fb.index) == pairs - fitted.corrected_pairs()
        return
    assert not len(fb.index)
    assert fb.scores["borrow"] < min(fb.scores["level"], fb.scores["wnomp"])
    assert fitted.borrowed > 0 and fitted.anchors is not None and fitted.rendered is not None
    assert len(fitted.anchors) == len(fitted.rendered.index) == pairs  # every pair: its own render or a borrowed one
    assert fitted.corrected_pairs() == pairs - fitted.borrowed < pairs
    borrowed = fitted.anchors.index[int(fitted.corrected_pairs()) :]  # the corrected pairs' anchors come first
    rows = np.array([g for _, g in borrowed])
    c = cells.numpy()[rows]
    stored = fitted.rendered.apply(torch.zeros(len(rows), bins), ids[c], rows)
    out = fitted.apply(stored, c, ids[c], rows)

    def mae(x: torch.Tensor) -> float:
        pred = torch.einsum("bmn,bn->bm", a2[c], x)
        true = torch.einsum("bmn,bn->bm", a2[c], truth[rows])
        return float((10.0 * torch.log10(pred.clamp_min(1e-12) / true)).abs().mean())

    level_only = PairCorrections(levels=fitted.levels).apply(field[rows], c, ids[c], rows)
    assert mae(out) < 0.5 < mae(level_only)


def test_the_mix_fits_wnomp_with_the_baselines_settings_and_may_choose_it_alone(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The dB mix's WNOMP is the baseline's (``wnomp_fallback``: the demo's selected settings) with each of
    ``MIX_ATOMS``' atom counts, so that a weight of 1 (a candidate) answers a posterior pair exactly as the baseline
    would with those atoms."""
    from rflscm.models.rflscm import corrections as module
    from rflscm.models.wnomp import WNOMPConfig

    assert 1.0 in module.MIX_WEIGHTS
    solvers: list[WNOMPConfig] = []
    solve = module._Fit.solve

    def spy(self, pairs, mask, levels, solver=module.SOLVER):  # type: ignore[no-untyped-def]
        solvers.append(solver)
        return solve(self, pairs, mask, levels, solver)

    monkeypatch.setattr(module._Fit, "solve", spy)
    baseline = WNOMPConfig(k_max=2, tolerance=0.05, weighting="none", residual_floor=0.1)
    pair_data, render, columns, _, _, _ = atom_problem(0)
    cfg = CorrectionsConfig(calibrate_levels=False, wnomp_atoms=True, lambda_groups=3, wnomp_fallback=baseline)
    visible = torch.ones(2, 40, dtype=torch.bool)
    fit_corrections(cfg, pair_data, 8, np.array([7, 8]), render, columns, seed=0, visible=visible)
    mixes = [s for s in solvers if s.weighting == "none"]
    assert {s.k_max for s in mixes} >= set(module.MIX_ATOMS)  # every atom count tried with the baseline's settings
    assert all(s.tolerance == 0.05 and s.residual_floor == 0.1 for s in mixes)


def test_the_mix_choice_is_paid_inside_the_pass_deadline(monkeypatch: pytest.MonkeyPatch) -> None:
    """The dB mix's choice (charged 1 s of the fake clock here) is made before the pairs are corrected, so the loop
    that corrects pairs while time is left stops in time for it: the pass ends within its deadline, and corrects fewer
    pairs than with a free choice."""
    from rflscm.models.rflscm import corrections as module

    pair_data, costly, columns_, truth, _, _, now = fallback_problem()
    visible = torch.ones(2, truth.shape[1], dtype=torch.bool)
    choose = module._mix_plan

    def run(charge: float) -> PairCorrections:
        def charged(*args, **kwargs):  # type: ignore[no-untyped-def]
            now[0] += charge
            return choose(*args, **kwargs)

        monkeypatch.setattr(module, "_mix_plan", charged)
        now[0] = 0.0
        cfg = CorrectionsConfig(calibrate_levels=False, wnomp_atoms=True, lambda_groups=3)
        return fit_corrections(
            cfg, pair_data, 8, np.array([7, 8]), costly, columns_, 0, time_left=lambda: 2.5 - now[0],
            clock=lambda: now[0], visible=visible,
        )  # fmt: skip

    free = run(0.0)
    paid = run(1.0)
    assert now[0] <= 2.5
    assert paid.mix is not None and free.mix is not None  # the mix was chosen both times
    assert 0 < paid.corrected_pairs() < free.corrected_pairs()


def test_the_mix_takes_the_later_pairs_wnomp_aps_solved_before_instead_of_solving_them_again(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Within a deadline, WNOMP's APS of every later pair is solved before the loop (the fallback's settings) and the
    mix's of the first pairs too; after the loop the mix, with the same settings, solves only the pairs that lack one
    (here none), takes the rest from there, and still gives every mixed pair WNOMP's APS of its own reports."""
    from rflscm.models.rflscm import corrections as module

    pair_data, costly, columns_, truth, _, _, now = fallback_problem()
    visible = torch.ones(2, truth.shape[1], dtype=torch.bool)
    calls: list[tuple[str, object, set[int]]] = []
    phase = ["before"]
    fallback, left_over_fn = module._Fit.fallback, module._left_over

    def spy(self, pairs, *args, **kwargs):  # type: ignore[no-untyped-def]
        solver = args[5] if len(args) >= 6 else kwargs.get("solver", module.SOLVER)
        calls.append((phase[0], solver, set(pairs.tolist())))
        return fallback(self, pairs, *args, **kwargs)

    def left_over(*args, **kwargs):  # type: ignore[no-untyped-def]
        phase[0] = "left over"
        out = left_over_fn(*args, **kwargs)
        phase[0] = "after"
        return out

    monkeypatch.setattr(module._Fit, "fallback", spy)
    monkeypatch.setattr(module, "_left_over", left_over)
    cfg = CorrectionsConfig(calibrate_levels=False, wnomp_atoms=True, lambda_groups=3)
    fitted = fit_corrections(
        cfg, pair_data, 8, np.array([7, 8]), costly, columns_, 0, time_left=lambda: 2.5 - now[0],
        clock=lambda: now[0], visible=visible,
    )  # fmt: skip
    assert fitted.mix is not None and len(fitted.mix.index) > 0 and fitted.posterior is not None
    solved = set().union(*(p for when, _, p in calls if when != "after"))  # the first pairs' and the later pairs'
    after = [p for when, solver, p in calls if when == "after" and solver == module.fallback_solver(cfg)]
    assert all(not (p & solved) for p in after)  # nothing solved twice with one setting
    mixed = {g for _, g in fitted.mix.index}
    assert mixed <= {g for _, g in fitted.posterior.index} and mixed <= solved
    later = set().union(*(p for when, _, p in calls if when == "left over"))
    assert mixed & later and mixed - later  # later pairs and first pairs are mixed


def test_corrections_change_an_owned_aps_in_place_and_leave_any_other_alone() -> None:
    """``apply(..., owned=True)`` (the model's own fresh tensor) gives the same APS as the copying call, written into
    that tensor; without it the caller's tensor is never changed, whichever corrections there are (levels, anchors, a
    posterior, WNOMP's fallback)."""
    pair_data, costly, columns_, truth, _, cells, now = fallback_problem()
    visible = torch.ones(2, truth.shape[1], dtype=torch.bool)
    cfg = CorrectionsConfig(wnomp_atoms=True, lambda_groups=3)
    fitted = fit_corrections(
        cfg, pair_data, 8, np.array([7, 8]), costly, columns_, 0, time_left=lambda: 2.5 - now[0],
        clock=lambda: now[0], visible=visible,
    )  # fmt: skip
    assert fitted.levels is not None and fitted.posterior is not None and fitted.fallback is not None
    assert len(fitted.posterior.index) and len(fitted.fallback.index)
    rows = np.arange(len(cells))
    c = cells.numpy()
    for parts in (fitted, dataclasses.replace(fitted, levels=None, anchors=None), PairCorrections()):
        aps = torch.rand(len(rows), truth.shape[1], generator=torch.Generator().manual_seed(3))
        before = aps.clone()
        copied = parts.apply(aps, c, np.array([7, 8])[c], rows)
        assert torch.equal(aps, before)  # not owned: untouched
        mine = aps.clone()
        in_place = parts.apply(mine, c, np.array([7, 8])[c], rows, owned=True)
        assert in_place.data_ptr() == mine.data_ptr()
        torch.testing.assert_close(in_place, copied, rtol=1e-6, atol=0.0)


def test_a_pass_whose_whole_fits_by_its_measured_cost_takes_every_level_pair() -> None:
    """``known`` (the pass's cost as ``measure_pass`` measured it on a chunk as the pass takes its pairs) prices a pair
    past a cell's first: where the whole pass fits the time left by it, the levels get all their pairs per cell, where
    the first renders' own cost (set-up included) would have left fewer."""
    from rflscm.models.rflscm.corrections import LEVEL_PAIRS_PER_CELL, PassTimes

    def levels_per_cell(known: PassTimes | None) -> int:
        rsrp, cells, timed, now = timed_problem(400, 4, seed=2)
        cfg = CorrectionsConfig(pair_posterior=False)
        args = (cfg, data(rsrp, cells), 1, np.array([7, 8, 9, 10]), timed, columns)
        fitted = fit_corrections(*args, seed=0, time_left=lambda: 1.0 - now[0], clock=lambda: now[0], known=known)
        return fitted.level_pairs

    assert levels_per_cell(None) < LEVEL_PAIRS_PER_CELL  # 10 ms a pair: 15 more per cell need 0.6 s of a 0.48 s share
    assert levels_per_cell(PassTimes(0.0, 0.001, 0.0, 0.0)) == LEVEL_PAIRS_PER_CELL  # 396 pairs × 1 ms fit in 0.96 s
