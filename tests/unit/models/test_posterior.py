"""The pair posterior: per-bin gains that fit a pair's reports under a ridge prior (rflscm.models.rflscm.posterior),
and RF-LSCM's use of it (``train.pair_posterior``)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch
from tiny_rflscm import tiny_config

from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.errors import CheckpointError
from rflscm.geometry import AngleGrid
from rflscm.models import load_model
from rflscm.models.rflscm import RFLSCM
from rflscm.models.rflscm.posterior import (
    LAMBDAS,
    PairPosterior,
    fit_gains,
    group_of,
    held_errors,
    predicted_change_db,
    report_groups,
    with_atoms,
    wnomp_atoms,
)
from rflscm.train import fit

GRID = AngleGrid.full_sphere(10, 12)


def problem(seed: int = 0, pairs: int = 6, beams: int = 12, bins: int = 20):
    """Random positive columns and APS, and reports made by true gains ``v_true`` (dB) on the APS."""
    g = torch.Generator().manual_seed(seed)
    cols = torch.rand(pairs, beams, bins, generator=g) ** 4
    x = torch.rand(pairs, bins, generator=g) + 0.1
    rest = 0.05 * torch.rand(pairs, beams, generator=g)
    v_true = 6.0 * torch.randn(pairs, bins, generator=g)
    resid = predicted_change_db(cols, x, rest, v_true)  # the reports' error against the field at v = 0
    return cols, x, rest, v_true, resid


def test_a_weak_ridge_fits_the_reports_and_a_strong_one_keeps_the_field() -> None:
    cols, x, rest, _, resid = problem()
    mask = torch.ones_like(resid, dtype=torch.bool)
    before = float(resid.abs().mean())
    weak = fit_gains(cols, x, rest, resid, mask, lam=1e-3, iterations=20)
    after = float((resid - predicted_change_db(cols, x, rest, weak)).abs().mean())
    assert before > 2.0 and after < 0.1 * before
    strong = fit_gains(cols, x, rest, resid, mask, lam=1e6)
    assert float(strong.abs().max()) < 1e-2


def test_reports_outside_the_mask_carry_no_information() -> None:
    cols, x, rest, _, resid = problem(seed=1)
    mask = torch.rand(resid.shape, generator=torch.Generator().manual_seed(2)) < 0.6
    v = fit_gains(cols, x, rest, resid, mask, lam=0.3)
    scrambled = torch.where(mask, resid, torch.full_like(resid, 1e3))
    torch.testing.assert_close(fit_gains(cols, x, rest, scrambled, mask, lam=0.3), v)
    none = fit_gains(cols, x, rest, resid, torch.zeros_like(mask), lam=0.3)
    assert float(none.abs().max()) == 0.0


def test_held_aside_errors_prefer_a_fit_that_predicts_held_aside_reports_and_else_none() -> None:
    cols, x, rest, _, resid = problem(seed=3, pairs=40)
    mask = torch.ones_like(resid, dtype=torch.bool)
    held = torch.rand(resid.shape, generator=torch.Generator().manual_seed(4)) < 0.2
    errors, count = held_errors(cols, x, rest, resid, mask, held)
    assert errors.shape == (1 + len(LAMBDAS), 40) and torch.equal(count, held.sum(1))
    torch.testing.assert_close(errors[0], torch.where(held, resid.abs(), 0.0).sum(1).double())  # row 0: the field
    mae = errors.sum(1) / count.sum()
    assert float(mae[1:].min()) < float(mae[0])
    # every beam sees its own bins only: fitted beams say nothing about held-aside ones, so no λ beats the field
    beams = resid.shape[1]
    diagonal = torch.eye(beams).expand(40, beams, beams).contiguous()
    noise = torch.randn(40, beams, generator=torch.Generator().manual_seed(5))
    alone, _ = held_errors(diagonal, torch.ones(40, beams), torch.zeros(40, beams), noise, mask, held)
    assert int(alone.sum(1).argmin()) == 0


def test_a_ridge_per_pair_is_each_pairs_own_fit() -> None:
    cols, x, rest, _, resid = problem(seed=6)
    mask = torch.ones_like(resid, dtype=torch.bool)
    lam = torch.tensor([0.1, 0.3, 1.0, 3.0, 0.1, 10.0])
    v = fit_gains(cols, x, rest, resid, mask, lam)
    for i, each in enumerate(lam.tolist()):
        one = slice(i, i + 1)
        torch.testing.assert_close(v[one], fit_gains(cols[one], x[one], rest[one], resid[one], mask[one], each))


def test_report_groups_split_pairs_by_report_count() -> None:
    counts = torch.tensor([2, 3, 3, 5, 8, 9, 20, 30, 31])
    edges = report_groups(counts, 3)
    assert edges.tolist() == [5, 13]  # quantiles 4.3 and 12.7, rounded up
    assert group_of(counts, edges).tolist() == [0, 0, 0, 1, 1, 1, 2, 2, 2]
    assert report_groups(counts, 1).numel() == 0 and group_of(counts, report_groups(counts, 1)).eq(0).all()
    same = torch.full((10,), 4)  # every pair reports as many beams: one group
    assert report_groups(same, 3).numel() == 0


def test_apply_moves_only_the_training_pairs_bins_and_survives_its_state() -> None:
    index = pd.MultiIndex.from_arrays([np.array([1, 1]), np.array([7, 8])], names=["cell_id", "grid_id"])
    bins = torch.tensor([[0, 3, 3], [5, 6, 2]])  # a repeated bin with a 0 dB gain (an empty slot) adds nothing
    gain = torch.tensor([[10.0, -10.0, 0.0], [3.0, 0.0, 0.0]])
    post = PairPosterior(index, bins, gain, 0.3, {0.3: 1.0, math.inf: 2.0})
    aps = torch.ones(3, 8)
    out = post.apply(aps, np.array([1, 2, 1]), np.array([8, 7, 7]))
    torch.testing.assert_close(out[1], aps[1])  # (2, 7) is no training pair
    assert float(out[2, 0]) == pytest.approx(10.0) and float(out[2, 3]) == pytest.approx(0.1)
    assert float(out[0, 5]) == pytest.approx(10**0.3, rel=1e-5) and float(out[0].sum()) == pytest.approx(7 + 10**0.3)
    again = PairPosterior.from_state(post.to_state(), num_bins=8)
    assert again is not None and again.lam == 0.3 and again.scores == post.scores
    torch.testing.assert_close(again.apply(aps, np.array([1, 2, 1]), np.array([8, 7, 7])), out, rtol=1e-3, atol=1e-3)
    assert PairPosterior.from_state(None, 8) is None


def test_atoms_join_the_candidates_centred_on_the_field_or_above_it() -> None:
    bins = torch.tensor([[4, 7, 9], [1, 2, 3]])
    x = torch.tensor([[1.0, 0.5, 0.2], [1.0, 1.0, 1.0]])
    atoms = torch.tensor([[7, 9, 30], [2, -1, -1]])  # on the field's bins (weaker, stronger), off them; none
    centre = torch.tensor([[0.1, 0.8, 0.3], [0.4, 5.0, 5.0]])
    out_bins, out_x, base = with_atoms(bins, x, atoms, centre)
    assert out_bins.tolist() == [[4, 7, 9, 4, 4, 30], [1, 2, 3, 1, 1, 1]]  # empty columns repeat a bin
    torch.testing.assert_close(out_x, torch.tensor([[1.0, 0.5, 0.2, 0, 0, 0], [1.0, 1.0, 1.0, 0, 0, 0]]))
    torch.testing.assert_close(base, torch.tensor([[0, 0, 0.6, 0, 0, 0.3], [0, 0, 0, 0, 0, 0.0]]))
    # an APS with these bases and no gains: the field, raised where an atom has more
    index = pd.MultiIndex.from_arrays([np.array([1, 1]), np.array([7, 8])], names=["cell_id", "grid_id"])
    post = PairPosterior(index, out_bins, torch.zeros(2, 6), 1.0, {}, base)
    aps = torch.zeros(2, 32)
    aps.scatter_(1, bins, x)
    out = post.apply(aps, np.array([1, 1]), np.array([7, 8]))
    assert float(out[0, 9]) == pytest.approx(0.8) and float(out[0, 30]) == pytest.approx(0.3)
    torch.testing.assert_close(out[1], aps[1])


def test_wnomp_atoms_find_the_bins_of_noiseless_reports_from_the_allowed_reports_only() -> None:
    g = torch.Generator().manual_seed(0)
    a = torch.rand(2, 24, 50, generator=g) ** 3
    cells = torch.tensor([0, 1, 0, 1])
    truth = torch.zeros(4, 50)
    truth[torch.arange(4), torch.tensor([3, 17, 40, 8])] = torch.tensor([1.0, 2.0, 0.5, 1.0])
    rsrp = torch.einsum("bmn,bn->bm", a[cells], truth)
    mask = torch.ones_like(rsrp, dtype=torch.bool)
    mask[3] = False  # the last pair may read none of its reports
    bins, gains = wnomp_atoms(lambda c: a[c], cells, rsrp, mask, k_max=2)
    assert bins[:3, 0].tolist() == [3, 17, 40] and bins[3].tolist() == [-1, -1]
    torch.testing.assert_close(gains[:3, 0], torch.tensor([1.0, 2.0, 0.5]), rtol=1e-4, atol=1e-6)
    garbled = torch.where(mask, rsrp, torch.full_like(rsrp, 1e6))  # what it may not read changes nothing
    assert torch.equal(wnomp_atoms(lambda c: a[c], cells, garbled, mask, k_max=2)[0], bins)
    # atoms per pair: each pair's as if solved alone with its own k_max (0: none)
    per_pair, _ = wnomp_atoms(lambda c: a[c], cells, rsrp, mask, k_max=torch.tensor([2, 0, 1, 2]))
    assert per_pair.shape == (4, 2) and per_pair[1].tolist() == [-1, -1] and int(per_pair[2, 1]) == -1
    alone, _ = wnomp_atoms(lambda c: a[c], cells[2:3], rsrp[2:3], mask[2:3], k_max=1)
    assert torch.equal(per_pair[0], bins[0]) and int(per_pair[2, 0]) == int(alone[0, 0])


@pytest.mark.parametrize(
    "damage",
    [
        lambda s: s.pop("gain_db"),
        lambda s: s.update(bins=torch.tensor([[0, 1]])),
        lambda s: s.update(gain_db=torch.full((2, 3), float("nan"))),
        lambda s: s.update(bins=torch.tensor([[0, 1, 99], [0, 1, 2]])),
        lambda s: s.update(lam="many"),
    ],
)
def test_damaged_posterior_state_is_refused_in_one_line(damage) -> None:
    index = pd.MultiIndex.from_arrays([np.array([1, 1]), np.array([7, 8])], names=["cell_id", "grid_id"])
    state = PairPosterior(index, torch.zeros(2, 3, dtype=torch.long), torch.zeros(2, 3), 1.0, {}).to_state()
    damage(state)
    with pytest.raises(CheckpointError, match="pair posterior is damaged"):
        PairPosterior.from_state(state, num_bins=8)


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    return load_scenario(tiny_scenario(tmp_path_factory.mktemp("posterior"), seed=0))


def round1_mae(model: RFLSCM, scenario) -> float:
    errs = []
    for beam_type in ("ssb", "csi"):
        pairs, measured = scenario.rsrp_table(1, beam_type)
        pred = model.predict_rsrp(scenario, 1, beam_type, pairs.reset_index(drop=True))[:, : measured.shape[1]]
        diff = measured - pred
        errs.append(np.abs(diff[np.isfinite(diff)]))
    return float(np.concatenate(errs).mean())


@pytest.mark.usefixtures("one_thread")
def test_the_posterior_fits_training_reports_leaves_training_alone_and_survives_a_checkpoint(
    scenario, tmp_path
) -> None:
    runs = {}
    for on in (True, False):
        torch.manual_seed(0)
        model = RFLSCM.build(tiny_config(train={"steps": 4}, corrections={"pair_posterior": on}), GRID)
        runs[on] = (model, fit(model, scenario, progress=False))
    model, summary = runs[True]
    post = model.corrections.posterior
    assert runs[False][0].corrections.posterior is None
    assert post is not None and math.isfinite(post.lam) and len(post.index) == len(model.corrections.anchors)
    assert post.scores[post.lam] < post.scores[math.inf]
    # training and the field's held-aside validation score do not change; the training reports fit better
    assert (
        summary["final_loss"] == runs[False][1]["final_loss"] and summary["val_mae_db"] == runs[False][1]["val_mae_db"]
    )
    assert round1_mae(model, scenario) < round1_mae(runs[False][0], scenario) - 0.3
    # round 2 reads the refined APS; a checkpoint carries the posterior
    pairs = pd.DataFrame({"cell_id": post.index.get_level_values(0)[:6], "grid_id": post.index.get_level_values(1)[:6]})
    moved = model.predict_rsrp(scenario, 2, "ssb", pairs)
    assert np.nanmax(np.abs(moved - runs[False][0].predict_rsrp(scenario, 2, "ssb", pairs))) > 0.1
    model.save(tmp_path / "p.ckpt")
    loaded = load_model(tmp_path / "p.ckpt")
    np.testing.assert_allclose(loaded.predict_rsrp(scenario, 2, "ssb", pairs), moved, atol=0.02)


@pytest.mark.usefixtures("one_thread")
def test_the_pass_after_training_shows_a_progress_bar_only_when_asked(scenario, capsys) -> None:
    torch.manual_seed(0)
    model = RFLSCM.build(tiny_config(train={"steps": 2}), GRID)
    fit(model, scenario, progress=False)
    assert "pair corrections" not in capsys.readouterr().err
    before = model.corrections.posterior
    model.finish_training(progress=True)
    assert "pair corrections" in capsys.readouterr().err and model.corrections.posterior is not before


@pytest.mark.usefixtures("one_thread")
def test_the_pass_after_training_renders_each_training_pair_once_and_measures_the_levels_on_it(
    scenario, monkeypatch
) -> None:
    torch.manual_seed(0)
    model = RFLSCM.build(tiny_config(train={"steps": 3}), GRID)
    fit(model, scenario, progress=False)
    levels, anchors = model.corrections.levels.clone(), model.corrections.anchors.copy()
    rendered: list[torch.Tensor] = []
    render = model._render_training
    monkeypatch.setattr(model, "_render_training", lambda pairs: (rendered.append(pairs.clone()), render(pairs))[1])
    model.finish_training()
    seen = torch.cat(rendered)
    assert seen.numel() == len(model.corrections.anchors) == seen.unique().numel()  # every pair with reports, once
    # the same corrections as a level correction measured on its own pairs
    torch.testing.assert_close(model.corrections.levels, levels)
    pd.testing.assert_series_equal(model.corrections.anchors, anchors)
