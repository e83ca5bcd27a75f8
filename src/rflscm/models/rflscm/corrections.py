"""The post-training pair corrections of RF-LSCM (and NeRF²-LSCM): a value object fitted once, applied in ``aps``.

After training, predictions carry (each switched in the config's ``corrections`` section):

* a *level* per cell and beam type (``calibrate_levels``): the median (measured − predicted) [dB] over the
  reported round-1 training beams of a few spread pairs per cell.  Under top-N or SINR reporting a model that
  cannot yet resolve the beams keeps every beam low to respect the bounds of the unreported ones, so its
  reported beams come out too weak; this removes that level error without touching the field;
* an *anchor* per training pair (``pair_anchors``): the mean error [dB] left on the pair's own reported round-1
  beams (SSB and CSI-RS pooled, after the level).  An under-trained field gets the angular shape right long
  before each grid's level; the pair's own reports pin that level.  Where the pair has no posterior, its mean is
  pulled toward its cell's mean anchor as far as its few reports leave it uncertain (:mod:`.anchors`);
* a *posterior* per training pair (``pair_posterior``): per-bin gains on the anchored APS fitting the same
  reports under a ridge prior centred on the field, λ chosen on held-aside reports (:mod:`.posterior`).

Validation beams are used by none, so the trainer's validation MAE stays a held-aside score of the field alone.
:func:`fit_corrections` renders every training pair with reports once; :class:`PairCorrections` holds the
result, applies it and saves it on its own (tensors only).

Within a time budget (``time_left``) the pass is sized to the time left: the pairs the levels and λ are measured
on come first (one per cell, then as many of the others as half the time left allows), then the other pairs in a
seeded random order (spread over cells and grids; in blocks of ``PASS_BLOCK``, each sorted by cell, so that a render
chunk spans few cells), a chunk at a time, while a chunk still fits.  When the pass
cannot reach every pair, the pairs left over get whichever predicts the held-aside reports best: WNOMP's APS of
their own reports (:mod:`.fallback`, solved in chunks of consecutive pairs), the APS rendered at the nearest corrected
grid of their cell with their own anchor (:mod:`.borrow`), both without a render, or the field with its level.
:func:`measure_pass` measures the pass's cost on two chunks, so that a budget run can keep time for it.
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np
import pandas as pd
import torch

from rflscm.data.pair_lookup import PairLookup
from rflscm.errors import CheckpointError
from rflscm.models.pairs import PairData
from rflscm.models.rflscm.anchors import deviations, report_mean, shrunk_anchors
from rflscm.models.rflscm.borrow import borrowed_reports, nearest_of_cell, own_anchor
from rflscm.models.rflscm.config import CorrectionsConfig
from rflscm.models.rflscm.fallback import (
    CLIP_DB,
    SOLVER,
    PairFallback,
    held_mae_db,
    predicted_reports,
    solve_reports,
)
from rflscm.models.rflscm.posterior import (
    HOLDOUT,
    LAMBDA_PAIRS,
    LAMBDAS,
    POSTERIOR_BINS,
    WNOMP_ATOMS,
    WNOMP_PRIORS,
    PairPosterior,
    fit_gains,
    group_of,
    held_errors,
    predicted_change_db,
    report_groups,
    with_atoms,
    wnomp_atoms,
)
from rflscm.models.wnomp import WNOMPConfig

PAIR_CHUNK = 64
"""Pairs per render chunk (A columns and APS rows stay small)."""
LEVEL_PAIRS_PER_CELL = 16
"""Training pairs per cell (evenly spaced) on which the level correction is measured."""
LEVEL_MIN_BEAMS = 10
"""A cell's own median needs this many reported beams of a type; fewer: the median over every cell."""

RenderFn = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
"""Training pairs ``[B]`` → their sparse APS ``(bins [B, K], values [B, K])`` and predicted reports ``[B, M]``."""
ColumnsFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]
"""``(cells [B], bins [B, K])`` → normalised A columns ``[B, M, K]``."""
TimeLeftFn = Callable[[], float]
"""Seconds left for the pass (a budget run's deadline); the pass stops starting chunks that would not fit."""
FIRST_SHARE = 0.5
"""Within a budget, the levels' and λ's pairs may take this share of the pass's time (fewer of them when short)."""
WARM_PAIRS = 2
"""A budget's pass renders this many pairs before it times a render (:func:`_first_pairs`): the first render sets up
what later ones reuse."""
FALLBACK_CHUNK = 1024
"""Pairs per WNOMP solve of the held-aside choice between the field and WNOMP's APS (:mod:`.fallback`)."""
FALLBACK_SOLVE = 4096
"""Within a budget, the left-over pairs' WNOMP solutions are found this many pairs at a time, each chunk started
only while it fits (~1 ms a pair: a tile of 53 k pairs spent 39 s of its 87-s pass on them)."""
PASS_BLOCK = 1024
"""The pairs the pass reaches after its first ones come in a seeded random order (spread over cells and grids where
the pass is cut) this many at a time, each block sorted by pair (so by cell): a render chunk's cost grows with the
cells it spans (800-grid city: 5.5 ms a pair for a chunk of 64 pairs over 42 cells, 3.5 ms for chunks of a few)."""
CHUNK_MARGIN = 1.25
"""A further chunk is started only when the time left exceeds this many times the slowest chunk so far."""
KEPT_BINS = 1152
"""A corrected pair's render is kept (:attr:`PairCorrections.rendered`) when it holds at most this many bins: HiTAM's
refined APS (β² K_C: 144 at the quick preset, 288 at the default, 8 bytes a bin; four times that with the coarse fill,
``hitam.outside: coarse``, the default), not the warm-up's coarse APS spread over every bin of the angle grid."""


@dataclass
class RoundOneCensor:
    """What round 1's silence says: a pair it did not report at a grid it visited was below ``cap_dbm`` (the reporting
    threshold, under rule ``threshold`` or ``top_n`` for SSB) on every SSB beam; its predictions are capped there
    (:func:`~rflscm.models.source.capped_aps`).  ``reported``: the (cell_id, grid_id) pairs with a round-1 report;
    ``visited``: the grid ids with any, sorted."""

    reported: pd.MultiIndex
    visited: np.ndarray
    cap_dbm: float

    def __post_init__(self) -> None:
        self.reported = self.reported.unique()  # get_indexer needs each pair once

    def caps_mw(self, cell_ids: np.ndarray, grid_ids: np.ndarray) -> np.ndarray:
        """``[N]`` the cap [mW] of each pair, NaN where round 1 reported it or never visited its grid."""
        cells = np.asarray(cell_ids, np.int64).reshape(-1)
        grids = np.asarray(grid_ids, np.int64).reshape(-1)
        known = PairLookup.kept_by(self, self.reported).rows(cells, grids) >= 0
        silent = np.isin(grids, self.visited) & ~known
        return np.where(silent, 10.0 ** (self.cap_dbm / 10.0), np.nan)

    def to_state(self) -> dict[str, torch.Tensor]:
        return {
            "cell_id": torch.as_tensor(self.reported.get_level_values(0).to_numpy(np.int64, copy=True)),
            "grid_id": torch.as_tensor(self.reported.get_level_values(1).to_numpy(np.int64, copy=True)),
            "visited": torch.as_tensor(np.asarray(self.visited, np.int64).copy()),
            "cap_dbm": torch.tensor(float(self.cap_dbm), dtype=torch.float64),
        }

    @classmethod
    def from_state(cls, state: object) -> RoundOneCensor | None:
        """Inverse of :meth:`to_state` (None: absent, as in checkpoints before it); damaged: a one-line error."""
        if state is None:
            return None
        damaged = "the checkpoint's round-1 silence table is damaged"
        keys = ("cell_id", "grid_id", "visited", "cap_dbm")
        if not isinstance(state, dict) or any(not isinstance(state.get(k), torch.Tensor) for k in keys):
            raise CheckpointError(f"{damaged} (expected tensors {', '.join(keys)}); retrain the model.")
        cells, grids, visited = (state[k].reshape(-1) for k in ("cell_id", "grid_id", "visited"))
        cap = state["cap_dbm"]
        if len(cells) != len(grids) or cap.numel() != 1 or not bool(torch.isfinite(cap).all()):
            raise CheckpointError(f"{damaged} (columns of different lengths or a non-finite cap); retrain the model.")
        if any(t.is_floating_point() or t.is_complex() for t in (cells, grids, visited)):
            raise CheckpointError(f"{damaged} (ids that are not integers); retrain the model.")
        reported = pd.MultiIndex.from_arrays([cells.long().numpy(), grids.long().numpy()], names=["cell_id", "grid_id"])
        return cls(reported.unique(), np.sort(visited.long().numpy()), float(cap.reshape(())))


@dataclass
class PairCorrections:
    """Fitted corrections: ``levels [C, 2]`` [dB] (SSB, CSI-RS per cell index), ``anchors`` [dB] indexed by
    (cell_id, grid_id) and ``posterior`` gains; each None when switched off."""

    levels: torch.Tensor | None = None
    anchors: pd.Series | None = None
    posterior: PairPosterior | None = None
    fallback: PairFallback | None = None
    """WNOMP's APS of the training pairs a budget's pass did not reach (:mod:`.fallback`), or None."""
    unseen_weight: float = 0.0
    """At a grid without an anchor, the weight of the model's APS at the cell's nearest anchored grid in the
    prediction (``corrections.unseen_blend_grids``, :func:`choose_blend`); 0: the grid's own APS alone."""
    mix: PairFallback | None = None
    """WNOMP's APS of posterior pairs' reports, averaged in dB into their SSB predictions (and their CSI-RS ones where
    :attr:`mix_csi` is None) with each row's weight (its group's, chosen on held-aside reports: :func:`_mix_plan`; the
    model's ``rsrp_mix``), or None."""
    censor: RoundOneCensor | None = None
    """The pairs round 1 was silent about at the grids it visited, capped at its threshold (the model's
    ``round1_caps``), or None (a reporting rule whose silence bound depends on interference: ``sinr``)."""
    mix_csi: PairFallback | None = None
    """The CSI-RS predictions' own dB mix (WNOMP's atoms and weights chosen on CSI-RS held-aside reports; no pair where
    they chose none), or None: :attr:`mix` serves both beam types (checkpoints written before the mix per beam type)."""
    rendered: PairFallback | None = None
    """The field's own APS (normalised, before any correction) of the pairs the pass rendered and corrected, as it
    rendered them at the final weights, so that no later prediction renders them again (:meth:`stored_rows`); None
    where the render is too wide to keep (HiTAM's warm-up: every bin) and in checkpoints written before it.  A pair
    that borrowed its APS (:mod:`.borrow`) holds the borrowed row here and its own anchor in :attr:`anchors`."""
    borrowed: int = 0
    """How many of the pairs in :attr:`anchors` borrowed their APS from a rendered neighbour (not corrected)."""
    level_pairs: int = 0
    """The training pairs per cell the levels were measured on (up to ``LEVEL_PAIRS_PER_CELL``; fewer where a budget's
    pass was short of time); the run's summary reports it, a checkpoint does not keep it (0 once loaded)."""
    anchor_kappa: float = math.nan
    """κ = σ²/τ² of the anchors' pull toward their cell's mean (:mod:`.anchors`: the reports' noise over the spread of
    the pairs' level errors; ∞ pooled whole, NaN not measured); the run's summary reports it, a checkpoint does not."""

    def mix_for(self, beam_type: str) -> PairFallback | None:
        """The dB mix of ``beam_type``'s predictions (:attr:`mix_csi` for CSI-RS where there is one, else :attr:`mix`)."""
        return self.mix_csi if beam_type == "csi" and self.mix_csi is not None else self.mix

    def apply(
        self, aps: torch.Tensor, cell_index: np.ndarray, cell_ids: np.ndarray, grid_ids: np.ndarray, owned: bool = False
    ) -> torch.Tensor:
        """``aps [N, K]`` (normalised) of pairs (``cell_index`` into the scene's cells, their ids and grid ids)
        with the SSB level, the anchors and the posterior applied.  Where the caller ``owned`` ``aps`` (a tensor of its
        own, made for this answer) it is changed in place and level and anchor scale each row in one pass: a fresh
        ``[N, K]`` tensor per step was most of RF-LSCM's answer time at the pairs it does not render."""
        cells = np.asarray(cell_ids, np.int64).reshape(-1)
        grids = np.asarray(grid_ids, np.int64).reshape(-1)
        factor = None  # [N] each row's level and anchor as a power ratio
        if self.levels is not None:
            index = torch.as_tensor(np.asarray(cell_index), device=aps.device)
            factor = torch.pow(10.0, self.levels.to(aps.device)[index, 0] / 10.0)
        if self.anchors is not None and len(self.anchors) and len(cells):
            at = PairLookup.kept_by(self, self.anchors.index).rows(cells, grids)
            shift = np.where(at >= 0, self.anchors.to_numpy(np.float32)[np.maximum(at, 0)], 0.0).astype(np.float32)
            shift = np.nan_to_num(shift, nan=0.0)
            anchor = torch.pow(10.0, torch.as_tensor(shift, device=aps.device) / 10.0)
            factor = anchor if factor is None else factor * anchor
        out = aps
        if factor is not None:
            out = out.mul_(factor[:, None]) if owned else out * factor[:, None]
        mine = owned or out is not aps  # a tensor of this call's own may be changed in place from here on
        if self.posterior is not None:
            out = self.posterior.apply(out, cells, grids, owned=mine)
            mine = mine or out is not aps
        if self.fallback is not None:
            out = self.fallback.apply(out, cells, grids, owned=mine)
        return out

    def stored_rows(self, cell_ids: np.ndarray, grid_ids: np.ndarray) -> np.ndarray:
        """``[N]`` each pair's row in :attr:`rendered` (its APS as the pass rendered it), −1 where it has none."""
        if self.rendered is None:
            return np.full(len(np.asarray(cell_ids).reshape(-1)), -1)
        return self.rendered.rows(cell_ids, grid_ids)

    def unrendered(self, cell_ids: np.ndarray, grid_ids: np.ndarray) -> np.ndarray:
        """bool ``[N]``: the pairs whose APS :meth:`apply` replaces whole (a model need not render them)."""
        if self.fallback is None:
            return np.zeros(len(np.asarray(cell_ids).reshape(-1)), bool)
        return self.fallback.rows(cell_ids, grid_ids) >= 0

    def corrected_pairs(self) -> float:
        """How many training pairs carry their own correction (an anchor, or else a posterior) on their own render."""
        if self.anchors is not None:
            return float(len(self.anchors) - self.borrowed)
        return float(len(self.posterior.index)) if self.posterior is not None else 0.0

    def level_offset_db(self, cell_index: np.ndarray, beam_type: str) -> np.ndarray | None:
        """CSI-RS predictions carry each cell's CSI-RS level relative to its SSB one (the APS carries the SSB one)."""
        if self.levels is None or beam_type != "csi":
            return None
        relative = (self.levels[:, 1] - self.levels[:, 0]).cpu().double().numpy()
        return relative[np.asarray(cell_index)]

    def to_state(self) -> dict[str, object]:
        """Tensors only (a checkpoint loads it with ``weights_only=True``)."""
        return {
            "levels": self.levels.detach().cpu().clone() if self.levels is not None else None,
            "anchors": _anchors_state(self.anchors),
            "posterior": self.posterior.to_state() if self.posterior is not None else None,
            "fallback": self.fallback.to_state() if self.fallback is not None else None,
            "unseen_weight": torch.tensor(float(self.unseen_weight), dtype=torch.float64),
            "mix": self.mix.to_state() if self.mix is not None else None,
            "censor": self.censor.to_state() if self.censor is not None else None,
            "mix_csi": self.mix_csi.to_state() if self.mix_csi is not None else None,
            "rendered": self.rendered.to_state() if self.rendered is not None else None,
            "borrowed": torch.tensor(int(self.borrowed), dtype=torch.int64),
        }

    @classmethod
    def from_state(
        cls, state: dict[str, object] | None, num_bins: int, device: torch.device | str = "cpu"
    ) -> PairCorrections:
        """Inverse of :meth:`to_state`; damaged entries are a one-line :class:`CheckpointError`."""
        if state is None:
            return cls()
        if not isinstance(state, dict):
            raise CheckpointError("the checkpoint's pair corrections are damaged (not a mapping).")
        levels = state.get("levels")
        weight = state.get("unseen_weight")  # absent in checkpoints written before the blend: no blend
        try:
            unseen_weight = 0.0 if weight is None else float(torch.as_tensor(weight).reshape(()))
        except (RuntimeError, TypeError, ValueError):
            unseen_weight = float("nan")
        if not 0.0 <= unseen_weight <= 1.0:
            raise CheckpointError("the checkpoint's pair corrections are damaged (the unseen-grid blend weight).")
        mix = PairFallback.from_state(state.get("mix"), num_bins, "dB mix of WNOMP's APS")  # absent before it: none
        mix_csi = PairFallback.from_state(state.get("mix_csi"), num_bins, "CSI-RS dB mix of WNOMP's APS")
        if any(m is not None and m.weight is None for m in (mix, mix_csi)):
            raise CheckpointError("the checkpoint's pair corrections are damaged (the dB mix has no weights).")
        return cls(
            torch.as_tensor(levels, dtype=torch.float32, device=device) if levels is not None else None,
            _anchors_from_state(state.get("anchors")),
            PairPosterior.from_state(state.get("posterior"), num_bins),  # type: ignore[arg-type]
            PairFallback.from_state(state.get("fallback"), num_bins),
            unseen_weight,
            mix,
            RoundOneCensor.from_state(state.get("censor")),
            mix_csi,
            PairFallback.from_state(state.get("rendered"), num_bins, "rendered APS of the corrected pairs"),
            _count(state.get("borrowed")),
        )


@torch.no_grad()
def fit_corrections(
    cfg: CorrectionsConfig,
    data: PairData,
    num_ssb: int,
    cell_ids: np.ndarray,
    render: RenderFn,
    columns: ColumnsFn,
    seed: int,
    progress: bool = False,
    time_left: TimeLeftFn | None = None,
    clock: Callable[[], float] = time.perf_counter,
    visible: torch.Tensor | None = None,
    render_rest: bool = False,
    extra_left: TimeLeftFn | None = None,
    known: PassTimes | None = None,
) -> PairCorrections:
    """Fit the switched-on corrections of the training ``data`` (``num_ssb`` SSB beams first, ``cell_ids`` of its
    cell indices) from one render of its pairs with reports (``render``, ``columns`` at the final weights;
    ``seed`` draws the posterior's held-aside reports and, within a budget, the order of the pairs; ``progress``: a
    bar; ``visible [C, N]``: the bins each cell's APS may hold, among which WNOMP's atoms are searched).  With
    ``time_left`` (seconds left, read on ``clock``'s time) the pass is sized to it: see the module's docstring;
    without it every pair with reports is corrected (the result does not depend on ``seed``'s order).  The pairs it
    corrects keep their render (:attr:`PairCorrections.rendered`): no later prediction renders them again.
    ``render_rest``: a caller within the same deadline would render the pairs the pass leaves where no fallback
    answers them (the demo's evaluation): once the held-aside choice keeps the field's level for them (or the fallback
    is off), the pass renders and keeps them itself, on its own clock, and corrects a pair only while the time left
    still renders every pair left after it; where its time cannot render them all, they get the better of WNOMP's
    APS and a borrowed APS (the budget's choice, ``PairFallback.scores["budget"]``).  ``extra_left``: the time left for the pairs
    corrected beyond the least (the levels' and λ's pairs and the fallback), where ``time_left`` runs past the
    budget's end to keep that least: a pass over its budget corrects no more pairs than its least needs.  ``known``: the
    pass's cost as :func:`measure_pass` last measured it (per pair on a chunk as the pass takes them, and the cells that
    chunk spans), which prices the whole pass where :func:`_first_pairs` asks whether it fits and, with the first
    renders, splits a chunk's cost into its pairs' and its cells' (without it, the pass's own first renders price all)."""
    from tqdm.auto import tqdm

    if not (cfg.calibrate_levels or cfg.pair_anchors or cfg.pair_posterior):
        return PairCorrections()
    fit = _Fit(cfg, data, num_ssb, len(cell_ids), render, columns, visible)
    pairs = torch.nonzero(data.observed.any(1)).squeeze(1)
    if not (cfg.pair_anchors or cfg.pair_posterior):  # the level alone: a few pairs per cell
        return PairCorrections(fit.levels(fit.render_pairs(fit.level_picks(), top=False)))
    fit.keep = True
    corrected = [0]
    owing = [0]  # pairs the pass must render, corrected or not (``render_rest``: those no fallback answers)
    each = [0.0]  # seconds a pair's render takes (measured on the first pairs)
    deadline = time_left
    if time_left is not None and render_rest:
        extra_deadline = extra_left

        def owed() -> float:  # the renders of the pairs left, were the next chunk corrected
            return each[0] * max(owing[0] - corrected[0] - PAIR_CHUNK, 0)

        def time_left() -> float:
            assert deadline is not None
            return deadline() - owed()

        if extra_deadline is not None:

            def extra_left() -> float:
                assert extra_deadline is not None
                return extra_deadline() - owed()

    per_pair = 2 if cfg.pair_posterior else 1  # a render, and a fit with the posterior
    bar = tqdm(total=pairs.numel() * per_pair, desc="pair corrections", unit="pair", disable=not progress, leave=False)
    subset = _spread(pairs, LAMBDA_PAIRS) if cfg.pair_posterior else pairs[:0]  # the pairs λ is chosen on
    if time_left is None:
        first = pairs
        rendered = fit.render_pairs(first, top=cfg.pair_posterior, bar=bar)
    else:
        first, rendered, subset = _first_pairs(fit, subset, time_left, clock, bar, known, pairs.numel())
        corrected[0] = first.numel()
        each[0] = fit.render_s
    levels = fit.levels(rendered) if cfg.calibrate_levels else None
    plan = _Plan()
    if cfg.pair_posterior and pairs.numel():
        # λ (and WNOMP's atoms) from held-aside reports of a spread subset of the pairs, per group of pairs with
        # about as many reports, then one fit per pair
        held = torch.rand(data.rsrp.shape, generator=torch.Generator().manual_seed(seed)) < HOLDOUT
        plan = _choose(fit, rendered, rendered.rows_of(subset.unique()), levels, held)
    fit.plan = plan
    fitting = cfg.pair_posterior and plan.fits()
    mixing = fitting and cfg.wnomp_atoms and visible is not None
    # the dB mix's choice reads only the λ pairs' renders: made before the pairs are corrected, whose loop then
    # stops in time for what follows it (made after, it ran ~3 s past a 222-cell pass's time)
    plans = _mix_plan(fit, rendered, rendered.rows_of(subset.unique()), levels, held, plan) if mixing else {}
    early: dict[WNOMPConfig, PairFallback] = {}  # the mix's WNOMP APS of the first pairs, solved before the loop
    if plans and time_left is not None:
        # whole, not cut by the time left: each first pair's render cost ~10× its solve, so this is bounded by what the
        # first pairs took already, and a pair whose group mixes never keeps the posterior alone for want of a solve
        mine = first[torch.isfinite(plan.of(data.observed[first].sum(1))[2]).to(first.device)]
        for solver, wanted in _mix_wanted(data, mine, plans, plan).items():
            if bool(wanted.any()):
                early[solver] = fit.fallback(mine[wanted.to(mine.device)], cell_ids, levels, {}, None, clock, solver)
    done, anchors, gains, bins_of, bases, mixed, kept = [], [], [], [], [], [], []
    spreads: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []  # per chunk: reports, noise, anchor alone
    later = _later_pairs(pairs, first, seed)
    left_over, choice = None, "level"
    if time_left is not None and cfg.wnomp_fallback and visible is not None and later.numel():
        # solved now for every later pair (no render: ~0.3 ms a pair), dropped below for the pairs the pass reaches
        on = subset if cfg.pair_posterior else first
        to_end = extra_left if extra_left is not None else time_left  # the budget's own end (nothing owed yet)

        def affordable(count: int) -> bool:  # the pass can render ``count`` pairs left over within the budget
            return not render_rest or each[0] * (count + CHUNK_MARGIN * PAIR_CHUNK) <= to_end()

        left_over, choice = _left_over(fit, rendered, on, later, cell_ids, levels, seed, time_left, clock, affordable)
    if render_rest and choice != "borrow":  # the pairs no fallback answers: rendered by the pass
        owing[0] = pairs.numel() - (len(left_over.index) if left_over is not None else 0)
    yielded = 0
    beyond = extra_left if extra_left is not None else time_left  # the pairs past the least: within the budget only
    render_chunk_s = PAIR_CHUNK * fit.render_s  # a later chunk's render, as the first pairs' chunks measured it
    for chunk in fit.corrected_chunks(rendered, later, levels, fitting, beyond, clock, bar, render_chunk_s):
        done.append(chunk.pairs)
        kept.append((chunk.aps_bins, chunk.aps_x))
        yielded += chunk.pairs.numel()
        corrected[0] = max(corrected[0], yielded)  # the first pairs were counted when they were rendered
        anchors.append(chunk.anchor)
        if cfg.pair_anchors:  # what the anchors' pull measures (:mod:`.anchors`), one entry per corrected chunk
            alone = torch.ones_like(chunk.anchor, dtype=torch.bool) if chunk.lam is None else ~torch.isfinite(chunk.lam)
            alone = alone.to(chunk.anchor.device)
            dev = deviations(chunk.resid[alone], chunk.mask[alone])
            spreads.append((chunk.mask.sum(1).cpu(), dev.cpu(), alone.cpu()))
        if chunk.top_bins is not None:
            assert chunk.lam is not None
            on = torch.isfinite(chunk.lam)  # a group that keeps the field: no reports fitted, gains 0
            mixed.append(chunk.pairs[on.to(chunk.pairs.device)])
            ridge = torch.where(on, chunk.lam, torch.ones_like(chunk.lam))
            gains.append(fit_gains(*chunk.fit_inputs(), chunk.resid, chunk.mask & on[:, None], ridge).cpu())
            bins_of.append(chunk.top_bins.cpu())
            bases.append(chunk.stored_base().cpu() if chunk.base is not None else None)
        bar.update(chunk.pairs.numel() * (per_pair - 1))
    reached = torch.cat(done) if done else pairs[:0]
    index = _pair_index(data, cell_ids, reached)
    corrected_index = index  # the pairs with the posterior's gains: the borrowed ones below have none
    left = later[~torch.isin(later, reached)]
    if left_over is not None and len(left_over.index):
        left = left[~torch.as_tensor(_pair_index(data, cell_ids, left).isin(left_over.index), device=left.device)]
    borrowed = pairs[:0]
    if choice == "borrow" and left.numel():  # the pairs left: the nearest rendered pair's APS, their own anchor
        sources = _Rendered(reached, data.rsrp[:0])
        if all(b is not None for b, _ in kept) and kept:
            sources.aps_bins = torch.cat([b for b, _ in kept if b is not None])
            sources.aps_x = torch.cat([x for _, x in kept if x is not None])
            level_db = _level_db(fit, levels, left)
            _, source, anchor, found = _borrowed(fit, sources, left, data.observed[left], level_db)
            at = source[found]
            kept.append((sources.aps_bins[at], sources.aps_x[at]))
            borrowed = left[found]
            anchors.append(anchor[found])
            reached, index = torch.cat([reached, borrowed]), index.append(_pair_index(data, cell_ids, borrowed))
            left = left[~found]
        if left.numel():  # no rendered pair of their cell (or no kept render) to borrow from: WNOMP's APS after all
            assert left_over is not None  # a choice of ``_left_over``
            left_over = fit.fallback(left, cell_ids, levels, left_over.scores, time_left, clock, fallback_solver(cfg))
    elif owing[0] and deadline is not None:  # the pairs left that no fallback answers, rendered with their level only
        only = fit.render_only(left, deadline, clock, bar, per_pair)
        if only.pairs.numel():
            kept.append((only.aps_bins, only.aps_x))
            reached = torch.cat([reached, only.pairs])
    bar.close()
    renders = _kept_renders(_pair_index(data, cell_ids, reached), kept)
    kappa = math.nan
    if spreads:  # the corrected pairs' anchors (the borrowed ones, after them, stay their own)
        count, pool, alone = (torch.cat(part) for part in zip(*spreads, strict=True))
        own = torch.cat(anchors[: len(spreads)])
        pulled, kappa = shrunk_anchors(own.cpu(), count, pool, data.cell_index[torch.cat(done)].cpu(), alone)
        anchors[: len(spreads)] = [pulled.to(own.device)]
    anchor_db = torch.cat(anchors).cpu().double().numpy() if anchors else np.zeros(0)
    anchor_series = pd.Series(anchor_db, index=index, name="anchor_db") if cfg.pair_anchors else None
    solved = left_over  # WNOMP's APS of every later pair, before the pass's own pairs leave it
    if left_over is not None:
        left_over = left_over.without(index)

    def corrections(
        posterior: PairPosterior | None, mix: PairFallback | None = None, mix_csi: PairFallback | None = None
    ) -> PairCorrections:  # what every outcome below returns, with its own posterior and dB mixes
        return PairCorrections(
            levels,
            anchor_series,
            posterior,
            left_over,
            mix=mix,
            mix_csi=mix_csi,
            rendered=renders,
            borrowed=int(borrowed.numel()),
            level_pairs=fit.level_per_cell,
            anchor_kappa=kappa,
        )

    if not cfg.pair_posterior:
        return corrections(None)
    if not gains:  # no choice of λ beat the field on held-aside reports: nothing to apply
        empty = pd.MultiIndex.from_arrays([np.zeros(0, np.int64)] * 2, names=["cell_id", "grid_id"])
        posterior = PairPosterior(
            empty,
            torch.zeros(0, 0, dtype=torch.long),
            torch.zeros(0, 0),
            *plan.summary(),
            None,
            plan.atom_scores,
            plan.groups,
        )
        return corrections(posterior)
    # a chunk's width is the field's bins and the most WNOMP atoms of its pairs' groups: chunks differ
    gain_db = _widened(gains).half().float()  # as a checkpoint stores it: a loaded model predicts the same
    with_base = [b if b is not None else torch.zeros_like(g) for b, g in zip(bases, gains, strict=True)]
    base = _widened(with_base) if any(b is not None for b in bases) else None
    lam, scores = plan.summary()
    posterior = PairPosterior(
        corrected_index, _widened(bins_of), gain_db, lam, scores, base, plan.atom_scores, plan.groups
    )
    mixes: dict[str, PairFallback | None] = {bt: None for bt in MIX_BEAM_TYPES}
    candidates = torch.cat(mixed).sort().values if mixed else torch.zeros(0, dtype=torch.long)
    if plans and candidates.numel():
        # no render: WNOMP's solve of the posterior pairs' own reports (~0.3 ms a pair), sized to the time left; per
        # beam type its atoms and each group's weight in the dB mix chosen above
        groups = group_of(data.observed[candidates].sum(1), plan.edges).cpu()
        weights = {bt: torch.tensor(w, dtype=torch.float32)[groups] for bt, (_, w, _) in plans.items()}
        solves: dict[WNOMPConfig, PairFallback] = {}  # one solve per setting: the beam types often choose the same
        candidate_index = _pair_index(data, cell_ids, candidates)
        for solver, wanted in _mix_wanted(data, candidates, plans, plan).items():
            # WNOMP's APS solved before the loop (the first pairs' for the mix; the later pairs' with the fallback's
            # settings) is taken from there (_with_solved) rather than solved twice: the time left goes to the rest
            have = [early.get(solver), solved if solver == fallback_solver(cfg) else None]
            for done_ in (h for h in have if h is not None and len(h.index)):
                wanted &= torch.as_tensor(~candidate_index.isin(done_.index), device=wanted.device)
            if bool(wanted.any()):
                pairs_ = candidates[wanted.to(candidates.device)]
                solves[solver] = fit.fallback(pairs_, cell_ids, levels, {}, time_left, clock, solver)
            else:
                solves[solver] = _no_mix()
        for bt, (solver, _, mix_scores) in plans.items():
            weight = weights[bt]
            with_mix = candidates[(weight > 0).to(candidates.device)]
            if not with_mix.numel():
                continue
            mixed_index = _pair_index(data, cell_ids, with_mix)
            mix = _with_solved(
                _with_solved(solves[solver].only(mixed_index), early.get(solver), mixed_index), solved, mixed_index
            )
            rows = torch.as_tensor(mixed_index.get_indexer(mix.index), dtype=torch.long)
            mixes[bt] = dataclasses.replace(mix, scores=mix_scores, weight=weight[weight > 0][rows])  # not shared
    mix_csi = mixes.get("csi")
    if mix_csi is None and mixes.get("ssb") is not None:  # CSI-RS chose no mix: not SSB's either
        mix_csi = _no_mix()
    return corrections(posterior, mix=mixes.get("ssb"), mix_csi=mix_csi)


def _mix_wanted(
    data: PairData,
    pairs: torch.Tensor,
    plans: dict[str, tuple[WNOMPConfig, tuple[float, ...], dict[str, float]]],
    plan: _Plan,
) -> dict[WNOMPConfig, torch.Tensor]:
    """Per WNOMP setting of the dB mix's ``plans`` (:func:`_mix_plan`), which of the posterior's ``pairs [P]`` some beam
    type mixes with it (their group's weight > 0), bool ``[P]``."""
    groups = group_of(data.observed[pairs].sum(1), plan.edges).cpu()
    out: dict[WNOMPConfig, torch.Tensor] = {}
    for solver, weights, _ in plans.values():
        mixes = torch.tensor(weights, dtype=torch.float32)[groups] > 0
        out[solver] = out[solver] | mixes if solver in out else mixes
    return out


def _pair_index(data: PairData, cell_ids: np.ndarray, pairs: torch.Tensor) -> pd.MultiIndex:
    """(cell_id, grid_id) of training ``pairs [P]`` (``cell_ids`` of the cell indices)."""
    at = pairs.cpu().numpy()
    ids = np.asarray(cell_ids, np.int64)[data.cell_index.cpu().numpy()[at]]
    return pd.MultiIndex.from_arrays([ids, data.grid_ids[at]], names=["cell_id", "grid_id"])


def _kept_renders(
    index: pd.MultiIndex, parts: list[tuple[torch.Tensor | None, torch.Tensor | None]]
) -> PairFallback | None:
    """The corrected pairs' renders (``parts``: each chunk's ``(bins, values)``, in ``index``'s order) as one table,
    or None where a chunk did not keep its render (too wide, :data:`KEPT_BINS`) or there is none."""
    if not parts or any(b is None or x is None for b, x in parts):
        return None
    bins = _widened([b for b, _ in parts if b is not None], none=-1).to(torch.int32).cpu()
    values = _widened([x for _, x in parts if x is not None], none=0).float().cpu()
    return PairFallback(index, bins, values)


def _no_mix() -> PairFallback:
    """A dB mix of no pair (a beam type whose held-aside reports chose none while the other's chose one)."""
    empty = pd.MultiIndex.from_arrays([np.zeros(0, np.int64)] * 2, names=["cell_id", "grid_id"])
    return PairFallback(empty, torch.zeros(0, 1, dtype=torch.long), torch.zeros(0, 1), {}, torch.zeros(0))


UNSEEN_WEIGHT = 0.5
"""The unseen-grid blend's weight without a hold-out (``corrections.unseen_blend_grids`` 0): the median of the
weights chosen on grids held out of training, never on B6's test grids.  Shipped scene, field regime: 0.7 (a B6
quick model trained without 22 more grids), 0.5 and 0.3 (the knob at 0.2 in B6 and B1 quick); ideal regime: 0.5
and 0.9 (the same two B6 ways); a procedural city, field regime: 0.3 (the first way), where 0.5 does worse than no
blend.  docs/DECISIONS.md, "Unseen grids (issue 28)"."""
BLEND_WEIGHTS = tuple(i / 10 for i in range(11))
"""The unseen-grid blend's candidate weights of the nearest anchored grid's APS (0: the grid's own alone)."""
BLEND_REACH = 3.0
"""An unseen grid is blended only when the cell's nearest anchored grid lies within this many times the anchored
grids' median spacing: B6's unseen grids are a median 10 m (one spacing) and a mean 11.5 m from theirs, and a
grid far from every measured one has nothing near to borrow from."""


def blend_grids(data: PairData, share: float, seed: int) -> np.ndarray:
    """The training grids held out of the field's training for the unseen-grid blend: a seeded ``share`` of the
    grids with reported training beams, sorted (empty for share 0, and at least one grid is always trained on)."""
    grids = np.unique(np.asarray(data.grid_ids)[data.observed.any(1).cpu().numpy()])
    num = min(int(round(share * len(grids))), len(grids) - 1)
    if share <= 0.0 or num < 1:
        return np.zeros(0, np.int64)
    return np.sort(np.random.default_rng(seed).permutation(grids)[:num]).astype(np.int64)


def choose_blend(
    own: torch.Tensor, nearest: torch.Tensor, measured: torch.Tensor, mask: torch.Tensor
) -> tuple[float, dict[float, float]]:
    """The weight ``w`` of :data:`BLEND_WEIGHTS` whose prediction (1 − w) × ``own`` + w × ``nearest`` (reports
    ``[B, M]``, linear, in ``measured``'s unit) has the least MAE [dB] on the ``mask``-ed ``measured`` reports, and
    every weight's MAE; the smaller weight on a tie, 0 when nothing is masked."""
    scores: dict[float, float] = {}
    if not bool(mask.any()):
        return 0.0, scores
    for w in BLEND_WEIGHTS:
        pred = ((1.0 - w) * own + w * nearest)[mask].double().clamp_min(1e-30)
        scores[w] = float((10.0 * torch.log10(measured[mask].double() / pred)).abs().mean())
    best = min(BLEND_WEIGHTS, key=lambda w: (scores[w], w))
    return best, scores


@dataclass(frozen=True)
class PassTimes:
    """The corrections' pass measured on one chunk [s]: ``setup_s`` once (the renderer's per-cell preparation on
    first use, for every cell), then per pair ``render_s`` (the render), ``prep_s`` (residuals, columns and, with
    the posterior, the most WNOMP atoms it may choose) and ``fit_s`` (one posterior fit)."""

    setup_s: float
    render_s: float
    prep_s: float
    fit_s: float
    solve_s: float = 0.0
    """Per pair, WNOMP's solve of its own reports (the fallback of a pair the pass does not reach)."""
    cells_per_pair: float = 1.0
    """The cells the timed chunk spans per pair (a chunk of a block: a few cells for 64 pairs); with a chunk of one pair
    per cell (1.0) it prices how a chunk's cost grows with the cells it spans (:func:`_first_pairs`)."""

    def total_s(self, cfg: CorrectionsConfig, pairs: int) -> float:
        """The whole pass over ``pairs`` pairs with reports as a budget runs it: setup, each pair once, the λ (and
        atoms) choice (every option's preparation and one fit per candidate λ on up to ``LAMBDA_PAIRS`` pairs), the dB
        mix's choice (:meth:`mix_s`) and, with the fallback on, WNOMP's solve of every pair, which a budget's pass
        makes before it knows how far it will reach (its safety net).  Without the last two a budget kept 19.0 s for
        a pass that took 21 s on the shipped demo's final weights, and left 300 of its 2 791 pairs uncorrected."""
        each = pairs * (self.render_s + self.prep_s + self.fit_s)
        net = pairs * self.solve_s if cfg.wnomp_fallback else 0.0
        if not cfg.pair_posterior:
            return self.setup_s + each + net
        options = 1 + (len(WNOMP_ATOMS) * len(WNOMP_PRIORS) if cfg.wnomp_atoms else 0)
        choice = options * min(pairs, LAMBDA_PAIRS) * (self.prep_s + len(LAMBDAS) * self.fit_s)
        return self.setup_s + each + choice + self.mix_s(cfg, min(pairs, LAMBDA_PAIRS)) + net

    def mix_s(self, cfg: CorrectionsConfig, lam_pairs: int) -> float:
        """The dB mix's choice (:func:`_mix_plan`, posterior and WNOMP's atoms on) on ``lam_pairs`` of λ's pairs: each
        pair's preparation, a posterior fit and WNOMP's solve at each of ``MIX_ATOMS``."""
        if not (cfg.pair_posterior and cfg.wnomp_atoms):
            return 0.0
        return lam_pairs * (self.prep_s + self.fit_s + len(MIX_ATOMS) * self.solve_s)

    def least_s(self, cfg: CorrectionsConfig, pairs: int, cells: int) -> float:
        """The least pass over ``pairs`` pairs of ``cells`` cells that a budget must leave: the levels' pairs rendered
        and, with the fallback on, WNOMP's APS of every pair's own reports (no render)."""
        levels = min(pairs, LEVEL_PAIRS_PER_CELL * cells) * (self.render_s + self.prep_s)
        return self.setup_s + levels + (pairs * self.solve_s if cfg.wnomp_fallback else 0.0)


@torch.no_grad()
def measure_pass(
    cfg: CorrectionsConfig,
    data: PairData,
    num_ssb: int,
    num_cells: int,
    render: RenderFn,
    columns: ColumnsFn,
    clock: Callable[[], float] = time.perf_counter,
    visible: torch.Tensor | None = None,
) -> PassTimes:
    """What the corrections' pass costs, on ``clock``: two chunks of pairs with reports rendered (the first spread over
    the cells, paying the renderer's per-cell setup, counted once per cell; the second a chunk of a block as the pass
    takes them, :func:`_later_pairs`, which is also what an evaluation's chunk costs), the second's residuals and columns
    prepared with the most WNOMP atoms the pass may choose (``wnomp_atoms`` on and ``visible`` given) and its
    gains fitted once (posterior on), and WNOMP's solve of a spread sample's reports (the fallback, when on).  All
    zero when every correction is off."""
    pairs = torch.nonzero(data.observed.any(1)).squeeze(1)
    if not (cfg.calibrate_levels or cfg.pair_anchors or cfg.pair_posterior) or not pairs.numel():
        return PassTimes(0.0, 0.0, 0.0, 0.0)
    first = _spread(pairs, PAIR_CHUNK).unique()  # every cell it touches pays the renderer's setup
    block = _later_pairs(pairs, pairs[:0], 0)[:PASS_BLOCK]  # a block as the pass takes its pairs, and a chunk of it
    start = max(0, (block.numel() - PAIR_CHUNK) // 2)
    second = block[start : start + PAIR_CHUNK]
    fit = _Fit(cfg, data, num_ssb, num_cells, render, columns, visible)
    atoms = max(WNOMP_ATOMS) if cfg.pair_posterior and cfg.wnomp_atoms and visible is not None else 0
    fit.plan = _Plan.uniform(atoms, 0, LAMBDAS[0])
    # the renderer's first call in a process builds what every later call reuses (its stored ray samples: 11 s on the
    # 222-cell city), which is no per-cell cost: paid before the clock, so the setup is not scaled by the cells
    fit.render_pairs(first[:1], top=cfg.pair_posterior)
    t0 = clock()
    fit.render_pairs(first, top=cfg.pair_posterior)
    t1 = clock()
    rendered = fit.render_pairs(second, top=cfg.pair_posterior)
    t2 = clock()
    chunks = list(fit.chunks(rendered, torch.arange(second.numel(), device=second.device), None, cfg.pair_posterior))
    t3 = clock()
    for chunk in chunks if cfg.pair_posterior else []:
        fit_gains(*chunk.fit_inputs(), chunk.resid, chunk.mask, LAMBDAS[0])
    t4 = clock()
    sample = _solve_sample(pairs)
    if cfg.wnomp_fallback:
        fit.solve(sample, data.observed[sample], None, fallback_solver(cfg))
    t5 = clock()
    n_first, n_second = first.numel(), second.numel()
    cells_first = int(data.cell_index[first].unique().numel())
    setup = max(0.0, (t1 - t0) - (t2 - t1) * n_first / n_second) * num_cells / max(cells_first, 1)
    render_s, prep_s, fit_s = ((b - a) / n_second for a, b in ((t1, t2), (t2, t3), (t3, t4)))
    spanned = int(data.cell_index[second].unique().numel()) / max(n_second, 1)
    return PassTimes(setup, render_s, prep_s, fit_s, (t5 - t4) / sample.numel(), spanned)


def _solve_chunks(pairs: torch.Tensor, size: int, seed: int = 0) -> list[torch.Tensor]:
    """``pairs`` sorted (so grouped by cell) in chunks of ``size``, the chunks in a seeded random order.  WNOMP's solve
    pays per cell of a chunk (its sensing matrix over every bin) about as much as for a few hundred pairs: a chunk of
    4 096 pairs drawn over the 222-cell city's 209 cells took 1.1–1.3 ms a pair, one of consecutive pairs (5 cells)
    0.14 ms.  The random order leaves chunks spread over the network where a budget stops the solve."""
    chunks = list(pairs.sort().values.split(size))
    order = torch.randperm(len(chunks), generator=torch.Generator().manual_seed(seed)).tolist()
    return [chunks[i] for i in order]


def _solve_sample(pairs: torch.Tensor) -> torch.Tensor:
    """``FALLBACK_CHUNK`` consecutive pairs from the middle of ``pairs`` sorted, as :func:`_solve_chunks` gives them:
    what WNOMP's solve per pair is timed on."""
    pairs = pairs.sort().values
    start = max(0, (pairs.numel() - FALLBACK_CHUNK) // 2)
    return pairs[start : start + FALLBACK_CHUNK]


def _spread(pairs: torch.Tensor, count: int) -> torch.Tensor:
    """Up to ``count`` of ``pairs`` evenly spread over their order (which groups them by cell)."""
    return pairs[torch.linspace(0, pairs.numel() - 1, min(pairs.numel(), count)).round().long()]


def _first_pairs(
    fit: _Fit,
    subset: torch.Tensor,
    time_left: TimeLeftFn,
    clock: Callable[[], float],
    bar: object,
    known: PassTimes | None = None,
    total: int = 0,
) -> tuple[torch.Tensor, _Rendered, torch.Tensor]:
    """Within a budget, the pairs rendered before any other: the levels' and λ's, ``(pairs, rendered, λ's pairs)``
    (:attr:`_Fit.render_s`: their render's seconds per pair, past each cell's first).  One pair per cell first (every
    cell needs its level), timed past its first ``WARM_PAIRS``
    (a model's first render sets up what every later one reuses: 1.3 s on the shipped scenario, 15 s at 222 cells);
    then the levels' other pairs (up to ``LEVEL_PAIRS_PER_CELL`` per cell) and λ's ``subset`` as far as
    ``FIRST_SHARE`` of the time left allows, once the time of the fallback's WNOMP solve of every other pair (timed on
    a spread sample) is kept aside; every one of them where the whole pass over its ``total`` pairs fits the time left,
    priced as its loop takes them: a pair at what ``known`` measured on a chunk of a block (``render_s + prep_s``, a
    posterior fit), or without it at what the first pairs cost.  The first pairs are priced by the pairs and the cells
    their chunks span, a chunk paying each cell's set-up (the renderer's, the columns'): the per-pair and per-cell
    parts come from the first pairs' own cost (a cell per pair) and ``known``'s (a few cells per chunk; without it,
    every pair at the first pairs' cost).
    When it does not, λ's pairs shrink first (to ``PAIR_CHUNK``), then the levels' pairs per cell: a CSI-RS level
    measured on too few pairs is off by many dB on every pair of its cells, which no later correction undoes (a
    tile measured on one pair per cell: +15 dB), while λ chosen on fewer pairs is only a coarser choice."""
    cfg = fit.cfg
    top = cfg.pair_posterior
    one = fit.level_picks(1)
    warm = min(WARM_PAIRS, one.numel() - 1) if one.numel() > 1 else 0
    rendered = fit.render_pairs(one[:warm], top=top, bar=bar) if warm else None
    begun = clock()
    rest = fit.render_pairs(one[warm:], top=top, bar=bar)
    render_s = (clock() - begun) / max(one.numel() - warm, 1)
    rendered = rest if rendered is None else _merged(rendered, rest)
    # a chunk's preparation (residuals, columns, the most WNOMP atoms λ's choice may try), timed on the same pairs
    atoms = max(WNOMP_ATOMS) if top and cfg.wnomp_atoms and fit.visible is not None else 0
    fit.plan = _Plan.uniform(atoms, 0, LAMBDAS[0])
    rows = torch.arange(min(one.numel(), PAIR_CHUNK), device=one.device)
    begun = clock()
    for _ in fit.chunks(rendered, rows, None, top):
        pass
    prep_s = (clock() - begun) / max(rows.numel(), 1)
    fit.plan = _Plan()
    fit._atom_cache.clear()  # timed with held=None: the choice's held-aside atoms are other ones
    options = 1 + (len(WNOMP_ATOMS) * len(WNOMP_PRIORS) if top and cfg.wnomp_atoms else 0)  # as PassTimes counts
    each = render_s + prep_s  # a pair rendered and corrected, its cell's set-up paid
    pair_s = known.render_s + known.prep_s if known is not None else each  # a further pair of a cell
    # a further λ pair: every option's preparation and a fit per λ (without ``known``, one set-up-paying preparation)
    choice_pair = options * (known.prep_s + len(LAMBDAS) * known.fit_s) if known is not None else prep_s
    safety_net = 0.0  # the fallback's WNOMP solve of every other pair comes after these: its time is kept
    if cfg.wnomp_fallback and fit.visible is not None:
        every = torch.nonzero(fit.data.observed.any(1)).squeeze(1)
        sample = _solve_sample(every)
        begun = clock()
        fit.solve(sample, fit.data.observed[sample], None, fallback_solver(cfg))
        solve_s = (clock() - begun) / max(sample.numel(), 1)
        safety_net = CHUNK_MARGIN * solve_s * (every.numel() - one.numel())
    left = time_left()  # the fallback's time kept, up to half: the levels' pairs keep a quarter of the pass at least
    room = FIRST_SHARE * (left - min(safety_net, FIRST_SHARE * max(left, 0.0)))
    cells = max(one.numel(), 1)
    # a chunk costs ``per_pair`` a pair and ``per_span`` a cell it spans (that cell's set-up: the renderer's, the
    # columns'): the first pairs (one per cell, a chunk spans a cell per pair) cost both a pair, ``known``'s chunk of a
    # block (a few cells) the first and its share of the second; so priced, a set of pairs costs what its chunks span
    per_pair, per_span = each, 0.0
    if known is not None and known.cells_per_pair < 1.0:
        per_span = max(each - (known.render_s + known.prep_s), 0.0) / (1.0 - known.cells_per_pair)
        per_pair = each - per_span
    reported = fit.data.cell_index[torch.nonzero(fit.data.observed.any(1)).squeeze(1)]
    per_cell_pairs = torch.bincount(reported, minlength=fit.num_cells)
    spread_cells: dict[int, torch.Tensor] = {}

    def priced(counts: torch.Tensor) -> float:
        # ``counts[c]`` pairs of cell c, in cell order (as sorted pairs are), rendered PAIR_CHUNK at a time
        counts = counts[counts > 0]
        start = torch.cumsum(counts, 0) - counts
        spans = (start + counts - 1) // PAIR_CHUNK - start // PAIR_CHUNK + 1
        return per_pair * float(counts.sum()) + per_span * float(spans.sum())

    def lambda_cells(lam_pairs: int) -> torch.Tensor:
        if lam_pairs not in spread_cells:
            picked = fit.data.cell_index[_spread(subset, lam_pairs)] if lam_pairs else reported[:0]
            spread_cells[lam_pairs] = torch.bincount(picked, minlength=fit.num_cells)
        return spread_cells[lam_pairs]

    def choice(lam_pairs: int, further: float = prep_s) -> float:
        # λ's choice and the dB mix's: every option on each of λ's pairs, the options sharing a cell's set-up (its
        # columns, its WNOMP solves), so a cell's first pair costs them all with that set-up (as timed: one pair per
        # cell) and its others ``further`` each (shipped scenario: 5.0 s for 512 pairs, 4.6 s priced with ``known``;
        # options × the first preparation priced 14–19 s)
        return options * prep_s * min(lam_pairs, cells) + further * max(lam_pairs - cells, 0)

    def cost(per_cell: int, lam_pairs: int) -> float:
        # the levels' pairs past each cell's first (timed above) and λ's, priced by the pairs and the cells their
        # chunks span: priced at ``known``'s chunk of one block alone, a 222-cell demo's pass took 7 pairs per cell and
        # ran 13 s past its share; at the first pairs' own cost alone, a 10-minute shipped run's pass took 6 of 16
        levels = (per_cell_pairs.clamp(max=per_cell) - 1).clamp_min(0)
        return priced(levels) + priced(lambda_cells(lam_pairs)) + choice(lam_pairs)

    fit_pair = known.fit_s if known is not None and cfg.pair_posterior else 0.0  # a posterior fit per pair
    # the whole pass as the loop takes its pairs (chunks of a block, ``known``'s measure): every pair corrected
    mix = known.mix_s(cfg, subset.numel()) if known is not None else 0.0  # the dB mix's choice on λ's pairs
    whole = (total - cells) * (pair_s + fit_pair) + choice(subset.numel(), choice_pair) + mix + safety_net
    least = min(PAIR_CHUNK, subset.numel())  # λ's pairs when short of time
    for per_cell in range(LEVEL_PAIRS_PER_CELL, 0, -1):
        fit.level_per_cell = per_cell
        if whole <= left or cost(per_cell, least) <= room:
            break
    if whole > left and cost(fit.level_per_cell, subset.numel()) > room and subset.numel():
        spread = min(max(least, cells), subset.numel())  # one pair per cell: each costs every option
        if cost(fit.level_per_cell, spread) > room:
            fits = (room - cost(fit.level_per_cell, 0)) / max(each + options * prep_s, 1e-12)
        else:  # past one pair per cell each more costs a render and a preparation
            fits = spread + (room - cost(fit.level_per_cell, spread)) / max(each + prep_s, 1e-12)
        subset = _spread(subset, max(least, int(fits)))
    first = torch.cat([fit.level_picks(), subset]).unique()
    more = first[~torch.isin(first, one)]
    begun = clock()
    extra = fit.render_pairs(more, top=top, bar=bar)
    if more.numel():
        render_s = (clock() - begun) / more.numel()
    fit.render_s = render_s
    return first, _merged(rendered, extra), subset


def _merged(a: _Rendered, b: _Rendered) -> _Rendered:
    """The rendered pairs of ``a`` and ``b`` (disjoint) as one, sorted by pair."""
    if not b.pairs.numel():
        return a
    pairs = torch.cat([a.pairs, b.pairs])
    order = torch.argsort(pairs)

    def both(x: torch.Tensor | None, y: torch.Tensor | None) -> torch.Tensor | None:
        return None if x is None or y is None else torch.cat([x, y])[order]

    pred = torch.cat([a.pred, b.pred])[order]
    out = _Rendered(pairs[order], pred, both(a.top_bins, b.top_bins), both(a.top_x, b.top_x))
    out.aps_bins, out.aps_x = both(a.aps_bins, b.aps_bins), both(a.aps_x, b.aps_x)
    return out


def _later_pairs(pairs: torch.Tensor, first: torch.Tensor, seed: int) -> torch.Tensor:
    """``pairs`` not in ``first``, in a seeded random order of blocks of ``PASS_BLOCK``, each block sorted (so by cell)
    (empty when ``first`` holds them all)."""
    rest = pairs[~torch.isin(pairs, first)]
    order = torch.randperm(rest.numel(), generator=torch.Generator().manual_seed(seed))
    rest = rest[order.to(rest.device)]
    block = torch.arange(rest.numel(), device=rest.device) // PASS_BLOCK
    span = int(rest.max()) + 1 if rest.numel() else 1
    return rest[torch.argsort(block * span + rest)]


@dataclass
class _Rendered:
    """Training pairs ``pairs [P]`` (sorted) rendered once: their predicted round-1 reports ``pred [P, M]``
    (normalised, uncorrected), optionally their strongest bins ``top_bins [P, n]`` (int32) with the APS there
    ``top_x [P, n]``, and optionally the whole render (``aps_bins``, ``aps_x``)."""

    pairs: torch.Tensor
    pred: torch.Tensor
    top_bins: torch.Tensor | None = None
    top_x: torch.Tensor | None = None
    aps_bins: torch.Tensor | None = None
    """``[P, K]`` the whole sparse APS's bins (int32) where the pass keeps it (:data:`KEPT_BINS`), else None."""
    aps_x: torch.Tensor | None = None
    """``[P, K]`` its values (normalised)."""

    def rows_of(self, pairs: torch.Tensor) -> torch.Tensor:
        """Rows of ``pairs`` (each one of :attr:`pairs`)."""
        rows = torch.searchsorted(self.pairs, pairs)
        if not bool((self.pairs[rows.clamp_max(max(self.pairs.numel() - 1, 0))] == pairs).all()):
            raise ValueError("pairs that were not rendered")
        return rows


@dataclass
class _PairChunk:
    """A chunk of training pairs ``pairs [B]`` as the corrections see them: ``anchor [B]`` [dB], ``resid [B, M]``
    measured − predicted [dB] after the corrections, ``mask [B, M]`` the reported training beams; with columns,
    the strongest bins ``top_bins [B, n]``, the APS there ``top_x [B, n]``, their columns ``cols [B, M, n]`` and
    the other bins' ``rest [B, M]`` (normalised) and each pair's ridge ``lam [B]`` (∞: no posterior); with WNOMP's
    atoms among them, ``base [B, n]`` the prior centre added at each bin (``resid`` then against the prediction with
    it) and ``level [B]`` [dB] the corrections applied before the posterior; ``aps_bins``, ``aps_x`` the pairs' whole
    render where the pass keeps it."""

    pairs: torch.Tensor
    anchor: torch.Tensor
    resid: torch.Tensor
    mask: torch.Tensor
    top_bins: torch.Tensor | None = None
    top_x: torch.Tensor | None = None
    cols: torch.Tensor | None = None
    rest: torch.Tensor | None = None
    base: torch.Tensor | None = None
    level: torch.Tensor | None = None
    lam: torch.Tensor | None = None
    aps_bins: torch.Tensor | None = None
    aps_x: torch.Tensor | None = None

    def fit_inputs(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(cols, prior centre, rest)``, the posterior's view of the chunk (made ``with_columns``)."""
        assert self.cols is not None and self.top_x is not None and self.rest is not None
        return self.cols, self.top_x if self.base is None else self.top_x + self.base, self.rest

    def stored_base(self) -> torch.Tensor:
        """:attr:`base` in the unit the posterior is applied in (after the level and anchor)."""
        assert self.base is not None and self.level is not None
        return self.base * torch.pow(10.0, self.level / 10.0)[:, None]


@dataclass
class _Fit:
    """What the fit reads: the config, the training data and the model's render and columns."""

    cfg: CorrectionsConfig
    data: PairData
    num_ssb: int
    num_cells: int
    render: RenderFn
    columns: ColumnsFn
    visible: torch.Tensor | None = None
    """bool ``[C, N]``: the bins of the angle grid each cell's APS may hold (WNOMP's atoms are searched there)."""
    level_per_cell: int = LEVEL_PAIRS_PER_CELL
    """Pairs per cell the levels are measured on (fewer within a budget too short for them: :func:`_first_pairs`)."""
    plan: _Plan = dataclasses.field(default_factory=lambda: _Plan())
    """Each pair's WNOMP atoms (0: none), their prior (``WNOMP_PRIORS``) and λ, by the pair's number of reports."""
    _atom_cache: dict[tuple[int, ...], tuple[torch.Tensor, torch.Tensor]] = dataclasses.field(default_factory=dict)
    """WNOMP's atoms of a chunk, kept while the choice tries prior centres on the same atoms (see :func:`_choose`)."""
    keep: bool = False
    """Keep each render whole (at most :data:`KEPT_BINS` wide): the pass's corrected pairs are not rendered again."""
    render_s: float = 0.0
    """Seconds a pair's render took in the pass (its first pairs'), within a budget."""

    def render_pairs(self, pairs: torch.Tensor, top: bool, bar: object = None) -> _Rendered:
        """Render ``pairs [P]`` (sorted) ``PAIR_CHUNK`` at a time: their predicted reports and, with ``top``, their
        ``POSTERIOR_BINS`` strongest bins and the APS there (``bar``: a tqdm bar)."""
        preds, tops, xs, whole = [], [], [], []
        for start in range(0, pairs.numel(), PAIR_CHUNK):
            bins, values, pred = self.render(pairs[start : start + PAIR_CHUNK])
            preds.append(pred)
            if self.keep and values.shape[1] <= KEPT_BINS:
                whole.append((bins.to(torch.int32), values))
            if top:
                best = torch.topk(values, min(POSTERIOR_BINS, values.shape[1]), dim=1).indices
                tops.append(bins.gather(1, best).to(torch.int32))  # kept for every pair: half the memory
                xs.append(values.gather(1, best))
            if bar is not None:
                bar.update(min(PAIR_CHUNK, pairs.numel() - start))  # type: ignore[attr-defined]
        pred = torch.cat(preds) if preds else torch.zeros(0, self.data.rsrp.shape[1], device=pairs.device)
        out = _Rendered(pairs, pred, torch.cat(tops) if tops else None, torch.cat(xs) if xs else None)
        if whole and len(whole) == len(preds):
            out.aps_bins, out.aps_x = torch.cat([b for b, _ in whole]), torch.cat([x for _, x in whole])
        return out

    def render_only(
        self, pairs: torch.Tensor, time_left: TimeLeftFn, clock: Callable[[], float], bar: object, per_pair: int
    ) -> _Rendered:
        """``pairs`` rendered (and kept, :attr:`keep`), ``PAIR_CHUNK`` at a time in their order (each chunk sorted), a
        chunk started only while ``CHUNK_MARGIN`` times the slowest so far (at first :attr:`render_s` per pair) fits
        in ``time_left``; the rendered ones in that order (``bar`` counts ``per_pair`` steps for each)."""
        parts: list[_Rendered] = []
        slowest = PAIR_CHUNK * self.render_s
        for start in range(0, pairs.numel(), PAIR_CHUNK):
            if time_left() < CHUNK_MARGIN * slowest:
                break
            begun = clock()
            parts.append(self.render_pairs(pairs[start : start + PAIR_CHUNK].sort().values, top=False))
            slowest = max(slowest, clock() - begun)
            if bar is not None:
                bar.update(parts[-1].pairs.numel() * per_pair)  # type: ignore[attr-defined]
        if not parts:
            return _Rendered(pairs[:0], self.data.rsrp[:0])
        out = _Rendered(torch.cat([p.pairs for p in parts]), torch.cat([p.pred for p in parts]))
        if all(p.aps_bins is not None for p in parts):
            out.aps_bins = torch.cat([p.aps_bins for p in parts if p.aps_bins is not None])
            out.aps_x = torch.cat([p.aps_x for p in parts if p.aps_x is not None])
        return out

    def level_picks(self, per_cell: int | None = None) -> torch.Tensor:
        """Up to ``per_cell`` (default :attr:`level_per_cell`) evenly spaced pairs with reports per cell (sorted)."""
        d = self.data
        reported = d.observed.any(1)
        picks = []
        count = self.level_per_cell if per_cell is None else per_cell
        for c in range(self.num_cells):
            p = torch.nonzero(reported & (d.cell_index == c)).squeeze(1)
            if p.numel():
                picks.append(p[torch.linspace(0, p.numel() - 1, min(p.numel(), count)).round().long()])
        return torch.cat(picks).unique() if picks else torch.zeros(0, dtype=torch.long, device=d.rsrp.device)

    def levels(self, rendered: _Rendered) -> torch.Tensor:
        """Median (measured − predicted) [dB] over the reported beams of the :meth:`level_picks` per cell and beam
        type (the median over every cell where a cell has fewer than ``LEVEL_MIN_BEAMS``; 0 where a type has none)."""
        d = self.data
        levels = torch.zeros(self.num_cells, 2)
        picks = self.level_picks()
        if not picks.numel():
            return levels.to(d.rsrp.device)
        pred = rendered.pred[rendered.rows_of(picks)]
        resid = 10.0 * torch.log10(d.rsrp[picks] / pred.clamp_min(1e-30))
        rows, beams = d.observed[picks].nonzero(as_tuple=True)
        r = resid[rows, beams].cpu().double().numpy()
        c = d.cell_index[picks][rows].cpu().numpy()
        t = (beams >= self.num_ssb).cpu().numpy()
        for beam_type in (0, 1):
            of_type = t == beam_type
            if not bool(of_type.any()):
                continue
            levels[:, beam_type] = float(np.median(r[of_type]))  # numpy: no size limit, mean of the middle pair
            for cell in range(self.num_cells):
                mine = of_type & (c == cell)
                if int(mine.sum()) >= LEVEL_MIN_BEAMS:
                    levels[cell, beam_type] = float(np.median(r[mine]))
        return levels.to(d.rsrp.device)

    def chunks(
        self,
        rendered: _Rendered,
        rows: torch.Tensor,
        levels: torch.Tensor | None,
        with_columns: bool = True,
        held: torch.Tensor | None = None,
    ) -> Iterator[_PairChunk]:
        """Rows ``rows`` of ``rendered``, ``PAIR_CHUNK`` at a time: each pair's anchor and, after ``levels`` and
        anchor, its residuals and (``with_columns``) its strongest bins with their columns, and WNOMP's atoms
        when switched on (fitted on the reports not ``held [P, M]`` aside)."""
        d = self.data
        beam_type = (torch.arange(d.rsrp.shape[1], device=d.rsrp.device) >= self.num_ssb).long()
        for start in range(0, rows.numel(), PAIR_CHUNK):
            at = rows[start : start + PAIR_CHUNK]
            batch = rendered.pairs[at]
            cells, pred = d.cell_index[batch], rendered.pred[at]
            resid = 10.0 * torch.log10(d.rsrp[batch] / pred.clamp_min(1e-30))
            if levels is not None:
                resid = resid - levels[cells][:, beam_type]
            mask = d.observed[batch]
            anchor = report_mean(resid, mask)
            if self.cfg.pair_anchors:
                resid = resid - anchor[:, None]
            chunk = _PairChunk(batch, anchor, resid, mask)
            if rendered.aps_bins is not None and rendered.aps_x is not None:
                chunk.aps_bins, chunk.aps_x = rendered.aps_bins[at], rendered.aps_x[at]
            if with_columns:
                assert rendered.top_bins is not None and rendered.top_x is not None
                chunk.top_bins, chunk.top_x = rendered.top_bins[at].long(), rendered.top_x[at]
                chunk.cols = self.columns(cells, chunk.top_bins)
                chunk.rest = (pred - torch.einsum("bmk,bk->bm", chunk.cols, chunk.top_x)).clamp_min(0.0)
                atoms, prior, chunk.lam = self.plan.of(d.observed[batch].sum(1))
                if int(atoms.max()) > 0:
                    level = levels[cells, 0] if levels is not None else torch.zeros_like(anchor)
                    self._add_atoms(chunk, level + anchor if self.cfg.pair_anchors else level, held, atoms, prior)
            yield chunk

    def corrected_chunks(
        self,
        rendered: _Rendered,
        later: torch.Tensor,
        levels: torch.Tensor | None,
        with_columns: bool,
        time_left: TimeLeftFn | None,
        clock: Callable[[], float],
        bar: object = None,
        render_chunk_s: float = 0.0,
    ) -> Iterator[_PairChunk]:
        """Every row of ``rendered``, then the ``later`` pairs rendered ``PAIR_CHUNK`` at a time (sorted within a
        chunk), as :meth:`chunks`; with ``time_left`` a later chunk is started only while ``CHUNK_MARGIN`` times its
        cost still fits.  That cost is the slowest later chunk so far (render and correction, timed as the caller
        consumes it); before the first, ``render_chunk_s`` (a chunk's render as measured on the rendered pairs) plus
        the slowest chunk of the rendered rows (their correction alone).  The first pairs' own cost (one pair per
        cell, each paying its cell's set-up) priced a later chunk 2.8× what it took, so a pass with the time to
        correct every pair corrected none past its first (etoile's ideal demo under load, DECISIONS "The pass prices
        its later chunks by their own cost")."""
        rows = torch.arange(rendered.pairs.numel(), device=rendered.pairs.device)
        correcting = 0.0  # the slowest chunk of the rendered rows: a chunk's correction without its render
        for start in range(0, rows.numel(), PAIR_CHUNK):
            begun = clock()
            yield from self.chunks(rendered, rows[start : start + PAIR_CHUNK], levels, with_columns)
            correcting = max(correcting, clock() - begun)
        slowest = render_chunk_s + correcting  # until a later chunk is timed
        timed = False
        for start in range(0, later.numel(), PAIR_CHUNK):
            if time_left is not None and time_left() < CHUNK_MARGIN * slowest:
                return
            begun = clock()
            part = later[start : start + PAIR_CHUNK].sort().values
            more = self.render_pairs(part, top=with_columns, bar=bar)
            yield from self.chunks(more, torch.arange(part.numel(), device=part.device), levels, with_columns)
            took = clock() - begun
            slowest = max(slowest, took) if timed else took
            timed = True

    def matrix(self, cell: int) -> torch.Tensor:
        """Cell index ``cell``'s normalised stacked sensing matrix ``[M, N]`` over every bin (``visible``'s)."""
        if self.visible is None:
            raise ValueError("WNOMP's solutions need the bins of the angle grid (``visible``)")
        every = torch.arange(self.visible.shape[1], device=self.data.rsrp.device)[None]
        return self.columns(torch.tensor([cell], device=every.device), every)[0]

    def solve(
        self, pairs: torch.Tensor, mask: torch.Tensor, levels: torch.Tensor | None, solver: WNOMPConfig = SOLVER
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """WNOMP's APS ``(bins, gains) [B, k]`` of ``pairs [B]`` from their ``mask``-ed reports (:mod:`.fallback`)."""
        d = self.data
        return solve_reports(self.matrix, d.cell_index[pairs], d.rsrp[pairs], mask, solver)

    def fallback(
        self,
        pairs: torch.Tensor,
        cell_ids: np.ndarray,
        levels: torch.Tensor | None,
        scores: dict[str, float],
        time_left: TimeLeftFn | None = None,
        clock: Callable[[], float] = time.perf_counter,
        solver: WNOMPConfig = SOLVER,
    ) -> PairFallback:
        """WNOMP's APS of ``pairs`` (``cell_ids`` of the cell indices) from all their training reports (WNOMP's
        ``solver`` settings).  With ``time_left``, in chunks of ``FALLBACK_SOLVE`` (:func:`_solve_chunks`) while the
        time left exceeds ``CHUNK_MARGIN`` times the slowest chunk so far (the first always: pairs beyond keep the
        field's level)."""
        d = self.data
        parts: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []
        slowest = 0.0
        size = FALLBACK_SOLVE if time_left is not None else max(pairs.numel(), 1)  # no budget: one solve
        for part in _solve_chunks(pairs, size):
            if parts and time_left is not None and time_left() < CHUNK_MARGIN * slowest:
                break
            begun = clock()
            parts.append((part, *self.solve(part, d.observed[part], levels, solver)))
            slowest = max(slowest, clock() - begun)
        if parts:  # in pair order, as without a budget
            pairs = torch.cat([p for p, _, _ in parts])
            order = torch.argsort(pairs)
            pairs = pairs[order]
            bins, gains = torch.cat([b for _, b, _ in parts])[order], torch.cat([g for _, _, g in parts])[order]
        else:
            bins, gains = self.solve(pairs, d.observed[pairs], levels, solver)
        kept = pairs.cpu().numpy()
        ids = np.asarray(cell_ids, np.int64)[d.cell_index.cpu().numpy()[kept]]
        index = pd.MultiIndex.from_arrays([ids, d.grid_ids[kept]], names=["cell_id", "grid_id"])
        return PairFallback(index, bins.cpu(), gains.cpu(), scores)

    def _add_atoms(
        self,
        chunk: _PairChunk,
        level: torch.Tensor,
        held: torch.Tensor | None,
        atoms: torch.Tensor,
        prior: torch.Tensor,
    ) -> None:
        """Add WNOMP's ``atoms [B]`` of the chunk's reports (not ``held`` aside) to its candidate bins, with the prior
        ``WNOMP_PRIORS[prior]`` (``[B]``); ``level [B]`` [dB]: the corrections before the posterior (the reports are
        that much above the field's own unit).  Where the prior lowers the field, so does the pair's anchor."""
        assert chunk.top_bins is not None and chunk.top_x is not None and chunk.cols is not None
        assert chunk.rest is not None
        if self.visible is None:
            raise ValueError("WNOMP's atoms need the bins each cell may hold")
        d, cells, visible = self.data, self.data.cell_index[chunk.pairs], self.visible.to(chunk.mask.device)
        every = torch.arange(visible.shape[1], device=cells.device)[None]
        mask = chunk.mask if held is None else chunk.mask & ~held[chunk.pairs.cpu()].to(chunk.mask.device)
        key = (held is None, *chunk.pairs.tolist(), *atoms.tolist())
        if key not in self._atom_cache:
            self._atom_cache[key] = wnomp_atoms(  # columns of the bins a cell cannot hold are zero: never an atom
                lambda c: self.columns(torch.tensor([c], device=cells.device), every)[0] * visible[c],
                cells,
                d.rsrp[chunk.pairs],
                mask,
                atoms,
            )
        atom_bins, atom_x = self._atom_cache[key]
        table = torch.tensor(WNOMP_PRIORS, dtype=level.dtype, device=level.device)[prior.to(level.device)]
        found = (atom_bins >= 0).any(1)
        lower = torch.where(found, table[:, 1], 0.0) if self.cfg.pair_anchors else torch.zeros_like(level)
        if bool((lower > 0).any()):  # the field's share: its APS (and the pair's anchor) ``lower`` dB down
            scale = torch.pow(10.0, -lower / 10.0).to(chunk.top_x.dtype)
            chunk.top_x, chunk.rest = chunk.top_x * scale[:, None], chunk.rest * scale[:, None]
            chunk.resid = chunk.resid + lower[:, None].to(chunk.resid.dtype)
            chunk.anchor = chunk.anchor - lower.to(chunk.anchor.dtype)
        centre = atom_x * torch.pow(10.0, -(level[:, None] + table[:, :1]) / 10.0)
        bins, x, base = with_atoms(chunk.top_bins, chunk.top_x, atom_bins, centre.to(chunk.top_x.dtype))
        cols = torch.cat([chunk.cols, self.columns(cells, bins[:, chunk.top_bins.shape[1] :])], 2)
        field = torch.einsum("bmk,bk->bm", cols, x) + chunk.rest
        raised = field + torch.einsum("bmk,bk->bm", cols, base)
        chunk.resid = chunk.resid - 10.0 * torch.log10(raised.clamp_min(1e-30) / field.clamp_min(1e-30))
        chunk.top_bins, chunk.top_x, chunk.cols, chunk.base, chunk.level = bins, x, cols, base, level


@dataclass
class _Plan:
    """The posterior's settings per group of pairs with about as many reports: ``edges`` (report counts, see
    :func:`~.posterior.report_groups`) and per group its WNOMP atoms ``atoms`` (0: none), their prior ``prior`` (an
    index of ``WNOMP_PRIORS``) and λ ``lam`` (∞: no posterior); ``groups`` records each group's choice and
    ``pooled`` the held-aside MAE [dB] of each λ for one choice over all pairs (``atom_scores``: the least over λ per
    number of atoms).  The default keeps the field everywhere."""

    edges: torch.Tensor = dataclasses.field(default_factory=lambda: torch.zeros(0, dtype=torch.long))
    atoms: tuple[int, ...] = (0,)
    prior: tuple[int, ...] = (0,)
    lam: tuple[float, ...] = (math.inf,)
    groups: list[dict[str, float]] = dataclasses.field(default_factory=list)
    pooled: dict[float, float] = dataclasses.field(default_factory=dict)
    pooled_lam: float = math.inf
    atom_scores: dict[int, float] = dataclasses.field(default_factory=dict)

    @classmethod
    def uniform(cls, atoms: int, prior: int, lam: float) -> _Plan:
        return cls(atoms=(atoms,), prior=(prior,), lam=(lam,))

    def of(self, counts: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Atoms, prior (index of ``WNOMP_PRIORS``) and λ ``[B]`` of pairs with ``counts [B]`` reports."""
        group = group_of(counts, self.edges).cpu()
        pick = [torch.tensor(v)[group].to(counts.device) for v in (self.atoms, self.prior, self.lam)]
        return pick[0].long(), pick[1].long(), pick[2].float()

    def fits(self) -> bool:
        """Whether some group applies a posterior."""
        return any(math.isfinite(lam) for lam in self.lam)

    def summary(self) -> tuple[float, dict[float, float]]:
        """``(λ, held-aside MAE per λ)`` of the one choice over all pairs (what :class:`PairPosterior` records)."""
        return self.pooled_lam, dict(self.pooled)


def _choose(
    fit: _Fit, rendered: _Rendered, rows: torch.Tensor, levels: torch.Tensor | None, held: torch.Tensor
) -> _Plan:
    """The posterior's plan: pairs of ``rows`` grouped by how many reports they have (``lambda_groups`` groups of
    about equal size), and per group the WNOMP atoms (none or, with ``wnomp_atoms``, one of ``WNOMP_ATOMS`` with one
    of the ``WNOMP_PRIORS``) and λ with the least error on the group's ``held`` aside reports (λ = ∞, no
    posterior, is always a candidate).  The same held-aside errors also give one choice over all pairs, recorded
    for comparison."""
    options = [(0, 0)]
    if fit.cfg.wnomp_atoms:
        options += [(a, c) for a in WNOMP_ATOMS for c in range(len(WNOMP_PRIORS))]
    lambdas = (math.inf, *LAMBDAS)
    errors: dict[tuple[int, int], torch.Tensor] = {}
    counts = fit.data.observed[rendered.pairs[rows]].sum(1).cpu()
    held_n = torch.zeros(0)
    for atoms, centre in options:
        fit.plan = _Plan.uniform(atoms, centre, LAMBDAS[0])
        parts, n_parts = [], []
        for chunk in fit.chunks(rendered, rows, levels, held=held):
            held_here = held[chunk.pairs.cpu()].to(chunk.resid.device)
            err_sums, held_count = held_errors(*chunk.fit_inputs(), chunk.resid, chunk.mask, held_here, LAMBDAS)
            parts.append(err_sums.cpu())
            n_parts.append(held_count.cpu())
        errors[(atoms, centre)] = torch.cat(parts, 1) if parts else torch.zeros(len(lambdas), 0, dtype=torch.float64)
        held_n = torch.cat(n_parts) if n_parts else torch.zeros(0, dtype=torch.long)
    fit.plan, fit._atom_cache = _Plan(), {}

    def best(select: torch.Tensor) -> tuple[float, float, int, int, float] | None:
        """(MAE, −λ, atoms, prior, λ) of the least held-aside error on the pairs ``select`` (None: none held)."""
        n = int(held_n[select].sum())
        if not n:
            return None
        candidates = [
            (float(err[i, select].sum()) / n, -lam, atoms, centre, lam)
            for (atoms, centre), err in errors.items()
            for i, lam in enumerate(lambdas)
            if atoms == 0 or math.isfinite(lam)  # with atoms, "∞" would be the atoms at their centres unfitted
        ]
        return min(candidates)

    every = torch.ones(counts.numel(), dtype=torch.bool)
    pooled = best(every)
    plan = _Plan()
    if pooled is None:
        return plan
    edges = report_groups(counts, fit.cfg.lambda_groups)
    group = group_of(counts, edges)
    picks = [best(group == g) or (math.nan, -math.inf, 0, 0, math.inf) for g in range(edges.numel() + 1)]
    plan.edges = edges
    plan.atoms, plan.prior, plan.lam = (tuple(p[k] for p in picks) for k in (2, 3, 4))  # type: ignore[assignment]
    lower = [int(counts[group == g].min()) if bool((group == g).any()) else 0 for g in range(edges.numel() + 1)]
    plan.groups = [
        {
            "min_reports": float(lo),
            "pairs": float(int((group == g).sum())),
            "atoms": float(p[2]),
            "centre_db": WNOMP_PRIORS[p[3]][0] if p[2] else math.nan,
            "field_db": WNOMP_PRIORS[p[3]][1] if p[2] else 0.0,
            "lam": p[4],
            "mae_db": p[0],
        }
        for g, (lo, p) in enumerate(zip(lower, picks, strict=True))
    ]
    n = int(held_n.sum())
    plan.pooled_lam = pooled[4]
    plan.pooled = {lam: float(errors[(pooled[2], pooled[3])][i].sum()) / n for i, lam in enumerate(lambdas)}
    plan.pooled[math.inf] = float(errors[(0, 0)][0].sum()) / n
    if fit.cfg.wnomp_atoms:
        plan.atom_scores = {
            a: min(float(err[i].sum()) / n for (k, _), err in errors.items() if k == a for i in range(1, len(lambdas)))
            for a in (0, *WNOMP_ATOMS)
        }
    return plan


def _left_over(
    fit: _Fit,
    rendered: _Rendered,
    on: torch.Tensor,
    later: torch.Tensor,
    cell_ids: np.ndarray,
    levels: torch.Tensor | None,
    seed: int,
    time_left: TimeLeftFn | None = None,
    clock: Callable[[], float] = time.perf_counter,
    affordable: Callable[[int], bool] | None = None,
) -> tuple[PairFallback, str]:
    """What answers the ``later`` pairs the pass may leave, and WNOMP's APS of them where that is the answer
    (:mod:`.fallback`): of the field with its level (``"level"``: rendered by whoever asks), WNOMP fitted on their
    reports (``"wnomp"``) and the APS of the nearest rendered pair of the cell with the pair's own anchor (``"borrow"``,
    :mod:`.borrow`: no render), the one that predicts the reports of the rendered pairs ``on`` held aside as the
    posterior's λ holds them (``seed``) best; where that is the field's level but ``affordable(len(later))`` says
    the pairs could not all be rendered within the budget, the better of the other two (the scores then say
    ``"budget": 1``).  Returns ``(WNOMP's APS of the pairs it answers, the choice)``, the scores (held-aside MAE [dB])
    kept in the first; with ``time_left``, as many of ``later`` (in their order) as fit (:meth:`_Fit.fallback`)."""
    errors, count = _held_scores(fit, rendered, on.unique(), levels, seed)
    scores = {name: err / count for name, err in errors.items()} if count else {}
    choice = min(scores, key=lambda name: scores[name]) if scores else "level"
    if choice == "level" and affordable is not None and not affordable(later.numel()):
        choice = min(("wnomp", "borrow"), key=lambda name: scores.get(name, math.inf))
        scores = {**scores, "budget": 1.0}
    answered = later if choice == "wnomp" else later[:0]
    return fit.fallback(answered, cell_ids, levels, scores, time_left, clock, fallback_solver(fit.cfg)), choice


def _held_scores(
    fit: _Fit, rendered: _Rendered, pairs: torch.Tensor, levels: torch.Tensor | None, seed: int
) -> tuple[dict[str, float], int]:
    """Summed held-aside |error| [dB] per answer a left-over pair may get (``"level"``: the field with ``levels``;
    ``"wnomp"``: WNOMP fitted on the other reports; ``"borrow"``: the nearest other rendered pair's APS of the cell
    with the anchor of the other reports, where ``rendered`` kept its renders), over the reports of the rendered
    ``pairs`` held aside as the posterior's λ holds them (``seed``), and their count."""
    d = fit.data
    held = torch.rand(d.rsrp.shape, generator=torch.Generator().manual_seed(seed)) < HOLDOUT
    sums = {"level": 0.0, "wnomp": 0.0, **({"borrow": 0.0} if rendered.aps_bins is not None else {})}
    count = 0
    for start in range(0, pairs.numel(), FALLBACK_CHUNK):
        part = pairs[start : start + FALLBACK_CHUNK]
        cells, observed = d.cell_index[part], d.observed[part]
        score = observed & held[part.cpu()].to(observed.device)
        level_db = _level_db(fit, levels, part)
        pred = rendered.pred[rendered.rows_of(part)] * torch.pow(10.0, level_db / 10.0)
        bins, gains = fit.solve(part, observed & ~score, levels, fallback_solver(fit.cfg))
        answers = {"level": pred, "wnomp": predicted_reports(fit.columns, cells, bins, gains)}
        if "borrow" in sums:
            answers["borrow"] = _borrowed(fit, rendered, part, observed & ~score, level_db, fallback=pred)[0]
        for name, predicted in answers.items():
            err, n = held_mae_db(d.rsrp[part], predicted, score)
            sums[name] += err
        count += n
    return sums, count


def _level_db(fit: _Fit, levels: torch.Tensor | None, pairs: torch.Tensor) -> torch.Tensor:
    """``[P, M]`` [dB] each report's level correction (its cell's, per beam type; 0 without levels)."""
    d = fit.data
    if levels is None:
        return torch.zeros_like(d.rsrp[pairs])
    beam_type = (torch.arange(d.rsrp.shape[1], device=pairs.device) >= fit.num_ssb).long()
    return levels[d.cell_index[pairs]][:, beam_type]


def _borrowed(
    fit: _Fit,
    rendered: _Rendered,
    targets: torch.Tensor,
    mask: torch.Tensor,
    level_db: torch.Tensor,
    fallback: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The ``targets``' reports predicted from the nearest other pair of their cell that ``rendered`` holds (its kept
    APS, :func:`~rflscm.models.rflscm.borrow.nearest_of_cell`) with each target's level ``level_db [T, M]`` and its own
    anchor over its ``mask``-ed reports: ``(predicted [T, M], source rows [T] (−1: none), anchor [T] [dB], found [T])``;
    a target without a source keeps ``fallback``'s row (else 0)."""
    assert rendered.aps_bins is not None and rendered.aps_x is not None
    d = fit.data
    source = nearest_of_cell(d, rendered.pairs, targets)
    found = source >= 0
    at = source.clamp_min(0)
    raw = borrowed_reports(fit.columns, d, targets, rendered.aps_bins[at], rendered.aps_x[at])
    anchor = own_anchor(d.rsrp[targets], raw, mask & found[:, None], level_db)
    predicted = raw * torch.pow(10.0, (level_db + anchor[:, None]) / 10.0)
    if fallback is not None:
        predicted = torch.where(found[:, None], predicted, fallback)
    return predicted, source, anchor, found


def fallback_solver(cfg: CorrectionsConfig) -> WNOMPConfig:
    """WNOMP's settings for the pairs a budget's pass does not reach: ``cfg.wnomp_fallback``'s where it gives them (the
    demo's selected baseline), else the baseline's defaults (:data:`~rflscm.models.rflscm.fallback.SOLVER`)."""
    return cfg.wnomp_fallback if isinstance(cfg.wnomp_fallback, WNOMPConfig) else SOLVER


MIX_ATOMS = (2, 4, 8)
"""WNOMP's atom counts (``k_max``) for the dB mix of the posterior pairs, one chosen on held-aside reports as the WNOMP
baseline's selection chooses among them (:data:`~rflscm.models.wnomp_select.CANDIDATES`)."""
MIX_WEIGHTS = (0.0, 0.25, 0.5, 0.75, 1.0)
"""Candidate weights of WNOMP's APS in a posterior pair's prediction, averaged in dB: (1 − w) × the posterior's +
w × WNOMP's fit of the pair's own reports (:class:`~rflscm.models.source.RsrpMix`).  0: the posterior alone; 1:
WNOMP's fit alone, where the held-aside reports say a weak field's posterior only adds error (a 114-cell ideal
city after 40 steps: SSB chose 1, CSI-RS 0.75; docs/DECISIONS.md, "WNOMP alone is a candidate of the dB mix")."""


MIX_BEAM_TYPES = ("ssb", "csi")
"""The dB mix is chosen per beam type: on the 800-grid city's held-aside reports WNOMP's 8 atoms predicted SSB best
(2.68 dB against 2.86 with 2) and its 2 atoms CSI-RS (2.68 against 3.62 with 8); a choice pooled over both, 3 CSI-RS
reports to 1 SSB, took CSI-RS's for both (docs/DECISIONS.md, "The dB mix per beam type")."""


def _mix_plan(
    fit: _Fit, rendered: _Rendered, rows: torch.Tensor, levels: torch.Tensor | None, held: torch.Tensor, plan: _Plan
) -> dict[str, tuple[WNOMPConfig, tuple[float, ...], dict[str, float]]]:
    """The dB mix of the posterior pairs per beam type (:data:`MIX_BEAM_TYPES`), chosen on that type's ``held``-aside
    reports of the λ pairs ``rows`` of ``rendered`` under the posterior's ``plan``: WNOMP with the baseline's settings
    (:func:`fallback_solver`: the demo's selected ones) and the :data:`MIX_ATOMS` count whose fit without the
    held-aside reports predicts them best, and, per group of ``plan``,
    the :data:`MIX_WEIGHTS` weight whose dB average of the posterior's and WNOMP's held-aside predictions errs least (a
    dB average's error is the same average of the two errors; each report's error counts at most ``CLIP_DB``; the
    smaller on a tie; 0 in a group that keeps the field or holds none of the type's reports).  Returns per beam type
    the settings, the weight per group and the scores (``k2``…: WNOMP alone; ``w0``…: each group's weight)."""
    d = fit.data
    fit.plan = plan
    base = fallback_solver(fit.cfg)  # the baseline's settings (the demo's selected ones), each atom count tried
    post, group_of_report, csi_report = [], [], []
    wnomp: dict[int, list[torch.Tensor]] = {k: [] for k in MIX_ATOMS}
    for chunk in fit.chunks(rendered, rows, levels, held=held):
        assert chunk.lam is not None
        held_here = held[chunk.pairs.cpu()].to(chunk.resid.device)
        on = torch.isfinite(chunk.lam)
        score = chunk.mask & held_here & on[:, None]
        if not bool(score.any()):
            continue
        ridge = torch.where(on, chunk.lam, torch.ones_like(chunk.lam))
        v = fit_gains(*chunk.fit_inputs(), chunk.resid, chunk.mask & ~held_here & on[:, None], ridge)
        post.append((chunk.resid - predicted_change_db(*chunk.fit_inputs(), v))[score].cpu())
        group = group_of(d.observed[chunk.pairs].sum(1), plan.edges)
        group_of_report.append(group[:, None].expand_as(score)[score].cpu())
        column = torch.arange(score.shape[1], device=score.device)[None, :].expand_as(score)
        csi_report.append((column[score] >= fit.num_ssb).cpu())
        cells = d.cell_index[chunk.pairs]
        for k in MIX_ATOMS:
            bins, gains = fit.solve(chunk.pairs, chunk.mask & ~held_here, None, dataclasses.replace(base, k_max=k))
            pred = predicted_reports(fit.columns, cells, bins, gains).clamp_min(1e-30)
            wnomp[k].append((10.0 * torch.log10(d.rsrp[chunk.pairs] / pred))[score].cpu())
    num_groups = len(plan.lam)
    if not post:
        return {bt: (base, (0.0,) * num_groups, {}) for bt in MIX_BEAM_TYPES}
    e_post, groups, is_csi = torch.cat(post).double(), torch.cat(group_of_report), torch.cat(csi_report)
    e_alone = {k: torch.cat(v).double() for k, v in wnomp.items()}
    out: dict[str, tuple[WNOMPConfig, tuple[float, ...], dict[str, float]]] = {}
    for bt in MIX_BEAM_TYPES:
        mine_bt = is_csi if bt == "csi" else ~is_csi
        if not bool(mine_bt.any()):
            out[bt] = (base, (0.0,) * num_groups, {})
            continue
        alone = {k: float(e[mine_bt].abs().clamp_max(CLIP_DB).mean()) for k, e in e_alone.items()}
        k_best = min(MIX_ATOMS, key=lambda k: (alone[k], k))
        scores: dict[str, float] = {f"k{k}": alone[k] for k in MIX_ATOMS}
        weights = []
        for g in range(num_groups):
            mine = mine_bt & (groups == g)
            if not bool(mine.any()):
                weights.append(0.0)
                continue
            e_p, e_w = e_post[mine], e_alone[k_best][mine]
            mix_err = {w: float(((1 - w) * e_p + w * e_w).abs().clamp_max(CLIP_DB).mean()) for w in MIX_WEIGHTS}
            weights.append(min(MIX_WEIGHTS, key=lambda w: (mix_err[w], w)))
            scores[f"w{g}"] = weights[-1]
        out[bt] = (dataclasses.replace(base, k_max=k_best), tuple(weights), scores)
    return out


def _widened(parts: list[torch.Tensor], none: int | None = None) -> torch.Tensor:
    """Row blocks ``[B_i, K_i]`` of sparse APS (bins, gains or prior bases) stacked at the widest ``K``, with columns
    that change nothing: a bins block is widened with ``none`` (a :class:`PairFallback`'s −1) or, without it, with its
    rows' first bin (a posterior's bins must be bins: as :func:`~rflscm.models.rflscm.posterior.with_atoms` leaves an
    atom that is not there), any other block with zeros (a gain of 0 dB, a base of 0)."""
    width = max(p.shape[1] for p in parts)

    def wide(p: torch.Tensor) -> torch.Tensor:
        extra = width - p.shape[1]
        if not extra:
            return p
        if p.is_floating_point():
            fill = p.new_zeros(p.shape[0], extra)
        else:
            fill = p[:, :1].expand(-1, extra) if none is None else p.new_full((p.shape[0], extra), none)
        return torch.cat([p, fill], 1)

    return torch.cat([wide(p) for p in parts])


def _with_solved(mix: PairFallback, solved: PairFallback | None, wanted: pd.MultiIndex) -> PairFallback:
    """``mix`` with the ``wanted`` pairs it lacks (its solve is cut to the time left) taken from ``solved``, WNOMP's
    APS of the pass's later pairs solved before the pass reached them (with the fallback's settings instead of the
    mix's atom choice): a pair the pass corrected is mixed either way, instead of keeping a posterior whose group chose
    the mix on held-aside reports."""
    if solved is None or not len(solved.index):
        return mix
    missing = wanted[~wanted.isin(mix.index)]
    rows = solved.index.get_indexer(missing)
    rows = rows[rows >= 0]
    if not rows.size:
        return mix
    take = torch.as_tensor(rows, dtype=torch.long)
    bins = _widened([mix.bins, solved.bins[take].to(mix.bins.dtype)], none=-1)
    gains = _widened([mix.gains, solved.gains[take].to(mix.gains.dtype)])
    return PairFallback(mix.index.append(solved.index[rows]), bins, gains, mix.scores)


def _count(value: object) -> int:
    """A checkpointed count (absent: 0); a damaged one is a one-line :class:`CheckpointError`."""
    if value is None:
        return 0
    try:
        count = int(torch.as_tensor(value).reshape(()))
    except (RuntimeError, TypeError, ValueError):
        count = -1
    if count < 0:
        raise CheckpointError("the checkpoint's pair corrections are damaged (the borrowed pairs' count).")
    return count


def _anchors_state(anchors: pd.Series | None) -> dict[str, torch.Tensor] | None:
    if anchors is None:
        return None
    cells, grids = (
        torch.as_tensor(anchors.index.get_level_values(k).to_numpy(np.int64, copy=True)) for k in ("cell_id", "grid_id")
    )
    return {"cell_id": cells, "grid_id": grids, "anchor_db": torch.as_tensor(anchors.to_numpy(np.float32))}


def _anchors_from_state(state: object) -> pd.Series | None:
    if state is None:
        return None
    keys = ("cell_id", "grid_id", "anchor_db")
    if not isinstance(state, dict) or any(k not in state for k in keys):
        raise CheckpointError(
            "the checkpoint's pair anchors are damaged (expected columns cell_id, grid_id, anchor_db)."
        )
    cols = {k: torch.as_tensor(state[k]).reshape(-1).numpy() for k in keys}
    if not len(cols["cell_id"]) == len(cols["grid_id"]) == len(cols["anchor_db"]):
        raise CheckpointError("the checkpoint's pair anchors are damaged (columns of different lengths).")
    if not np.isfinite(cols["anchor_db"]).all():
        raise CheckpointError("the checkpoint's pair anchors are damaged (non-finite values); retrain the model.")
    index = pd.MultiIndex.from_arrays(
        [cols["cell_id"].astype(np.int64), cols["grid_id"].astype(np.int64)], names=["cell_id", "grid_id"]
    )
    return pd.Series(cols["anchor_db"].astype(np.float64), index=index, name="anchor_db")
