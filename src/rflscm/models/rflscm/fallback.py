"""The APS of the training pairs that a budget's pass after training cannot reach (issue 29).

Within a ``--minutes`` budget the pass after training (:mod:`~rflscm.models.rflscm.corrections`) renders as
many training pairs as fit; on a large network most pairs are left over (at 222 cells, a few thousand of tens
of thousands) and would keep the field's APS with the per-cell level only.  A pair's own round-1 reports still
say much about its APS, and reading them needs no render: WNOMP's sparse solution of those reports (through the
model's own round-1 sensing columns) is the pair posterior's λ → 0 limit with WNOMP's atoms, at ~0.1 ms a pair
instead of the render's tens of ms.

Whether the left-over pairs get it is chosen like the posterior's λ, on held-aside reports of the pairs the pass
did render: WNOMP fitted on the other reports against the field with its level (the same held-aside reports,
the same score).  The better one is kept for every left-over pair; :class:`PairFallback` holds the solutions
(bins and normalised path gains per pair), and a model answers those pairs with them, without rendering.

The model's CSI-RS predictions carry a per-cell level relative to SSB (``level_offset_db``); a left-over pair's do
not (the model asks :meth:`PairCorrections.unrendered`), so that its predictions are WNOMP's fit of its reports.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import torch

from rflscm.data.pair_lookup import PairLookup
from rflscm.errors import CheckpointError
from rflscm.models.rflscm.posterior import pair_rows
from rflscm.models.wnomp import CellMatrices, WNOMPConfig, solve_jobs

SOLVER = WNOMPConfig()
"""The WNOMP baseline's default settings (atoms, tolerance, weighting): a left-over pair gets what WNOMP would fit
(``corrections.wnomp_fallback`` may give other settings, as the demo gives its selected baseline's)."""


def solve_reports(
    matrix: Callable[[int], torch.Tensor],
    cells: torch.Tensor,
    rsrp: torch.Tensor,
    mask: torch.Tensor,
    solver: WNOMPConfig = SOLVER,
) -> tuple[torch.Tensor, torch.Tensor]:
    """WNOMP's solution of each pair's ``mask``-ed reports: bins ``[B, k]`` (−1: none) and gains ``[B, k]``.

    Args:
        matrix: cell index → the model's normalised stacked sensing matrix ``[M, N]`` (SSB rows, then CSI-RS).
        cells: each pair's cell index ``[B]``.
        rsrp: the reports ``[B, M]`` (normalised linear; the gains come out in the unit ``rsrp / a_norm``).
        mask: ``[B, M]`` the reports to fit.
        solver: WNOMP's settings (``k = solver.k_max``).
    """
    r = torch.where(mask, rsrp, torch.full_like(rsrp, math.nan)).double()
    bins = torch.full((rsrp.shape[0], solver.k_max), -1, dtype=torch.long)
    gains = torch.zeros(rsrp.shape[0], solver.k_max, dtype=torch.float32)
    # the WNOMP baseline's own jobs (a cell's pairs in chunks) over its worker threads
    of_cell, r_np = cells.cpu().numpy(), r.cpu().numpy()
    matrices = CellMatrices(lambda cell: matrix(cell).double())
    jobs = []
    for cell in np.unique(of_cell):
        rows = np.flatnonzero(of_cell == cell)
        for s in range(0, len(rows), solver.chunk_size):
            jobs.append((int(cell), rows[s : s + solver.chunk_size], r_np[rows[s : s + solver.chunk_size]]))
            matrices.expect(int(cell))
    for rows, idx, val in solve_jobs(jobs, matrices, solver, None, torch.device("cpu")):
        at = torch.as_tensor(rows, dtype=torch.long)
        bins[at], gains[at] = torch.as_tensor(idx), torch.as_tensor(val).clamp_min(0.0).float()
    return bins.to(rsrp.device), gains.to(rsrp.device)


def predicted_reports(
    columns: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    cells: torch.Tensor,
    bins: torch.Tensor,
    gains: torch.Tensor,
) -> torch.Tensor:
    """The reports ``[B, M]`` (normalised) that the sparse APS ``(bins, gains) [B, k]`` predict through
    ``columns`` (``(cells [B], bins [B, k])`` → ``[B, M, k]``)."""
    cols = columns(cells, bins.clamp_min(0))
    return torch.einsum("bmk,bk->bm", cols, torch.where(bins >= 0, gains, 0.0))


CLIP_DB = 20.0
"""A held-aside report's error counts at most this much in the choice: a sparse solution that puts no power on a
held beam's pattern predicts it at ~0 (hundreds of dB off), and a few such beams would outweigh every other report
(measured on the shipped scenario: WNOMP's held-aside median error 5.2 dB against the field's 9.2 dB, its mean
15.7 dB against 11.5 dB, its largest 313 dB)."""


def held_mae_db(measured: torch.Tensor, predicted: torch.Tensor, score: torch.Tensor) -> tuple[float, int]:
    """Sum of |measured − predicted| [dB], each at most ``CLIP_DB``, over the ``score`` mask, and how many."""
    n = int(score.sum())
    if not n:
        return 0.0, 0
    err = 10.0 * torch.log10(measured[score] / predicted[score].clamp_min(1e-30))
    return float(err.abs().clamp_max(CLIP_DB).sum()), n


@dataclass
class PairFallback:
    """WNOMP's APS of the training pairs the pass did not reach: row ``i`` of ``bins [P, k]`` (−1: none) and
    ``gains [P, k]`` (the unit the corrections are applied in) belongs to pair ``index[i]`` = (cell_id, grid_id);
    ``scores`` the held-aside MAE [dB] that chose it (``"level"``: the field with its level, ``"wnomp"``)."""

    index: pd.MultiIndex
    bins: torch.Tensor
    gains: torch.Tensor
    scores: dict[str, float] = field(default_factory=dict)
    weight: torch.Tensor | None = None
    """``[P]`` in (0, 1]: as the posterior pairs' dB mix (:mod:`.corrections`), each row's weight; None otherwise."""

    def rows(self, cell_ids: np.ndarray, grid_ids: np.ndarray) -> np.ndarray:
        """Row of each pair (``cell_ids``, ``grid_ids`` [N]) in :attr:`index`, −1 where it has none."""
        return PairLookup.kept_by(self, self.index).rows(cell_ids, grid_ids)

    def apply(self, aps: torch.Tensor, cell_ids: np.ndarray, grid_ids: np.ndarray, owned: bool = False) -> torch.Tensor:
        """``aps [N, K]`` with each left-over pair's row replaced by its WNOMP APS; in place where the caller ``owned``
        ``aps`` (a tensor of its own, made for this answer), else on a copy."""
        at = self.rows(cell_ids, grid_ids)
        dst = np.flatnonzero(at >= 0)
        if not dst.size:
            return aps
        src = torch.as_tensor(at[dst], dtype=torch.long)
        bins, gains = self.bins[src].to(aps.device), self.gains[src].to(aps.device, aps.dtype)
        out = aps if owned else aps.clone()
        # the rows cleared where they are and the atoms added there: no [rows, K] tensor of their own
        where = torch.as_tensor(dst, dtype=torch.long, device=aps.device)
        out[where] = 0.0
        values = torch.where(bins >= 0, gains, torch.zeros_like(gains))
        out.index_put_((where[:, None].expand_as(bins), bins.clamp_min(0)), values, accumulate=True)
        return out

    def without(self, index: pd.MultiIndex) -> PairFallback:
        """The same without the pairs of ``index`` (those the pass reached and corrected itself)."""
        keep = ~self.index.isin(index)
        if bool(keep.all()):
            return self
        rows = torch.as_tensor(np.flatnonzero(keep), dtype=torch.long)
        weight = None if self.weight is None else self.weight[rows]
        return PairFallback(self.index[keep], self.bins[rows], self.gains[rows], self.scores, weight)

    def only(self, index: pd.MultiIndex) -> PairFallback:
        """The same restricted to the pairs of ``index`` it holds (in its own order)."""
        return self.without(self.index[~self.index.isin(index)])

    def to_state(self) -> dict[str, object]:
        narrow = not self.bins.numel() or int(self.bins.max()) < 2**15  # the angle grid's 6 552 bins fit 16 bits
        return {
            "cell_id": torch.as_tensor(self.index.get_level_values(0).to_numpy(np.int64, copy=True)),
            "grid_id": torch.as_tensor(self.index.get_level_values(1).to_numpy(np.int64, copy=True)),
            "bins": self.bins.to(torch.int16 if narrow else torch.int32).cpu().clone(),
            "gains": self.gains.float().cpu().clone(),
            "scores": {k: float(v) for k, v in self.scores.items()},
            **({} if self.weight is None else {"weight": self.weight.float().cpu().clone()}),
        }

    @classmethod
    def from_state(cls, state: object, num_bins: int, what: str = "left-over pairs' APS") -> PairFallback | None:
        """Inverse of :meth:`to_state`; refuses damaged data in one line (:class:`CheckpointError`) naming ``what``."""
        if state is None:
            return None
        damaged = f"the checkpoint's {what} is damaged"
        keys = ("cell_id", "grid_id", "bins", "gains")
        if not isinstance(state, dict) or any(k not in state for k in keys):
            raise CheckpointError(f"{damaged} (expected {', '.join(keys)}); retrain the model.")
        cells, grids, bins, gains = pair_rows(state, "gains", damaged)
        if not bool(torch.isfinite(gains).all()) or bool((gains < 0).any()):
            raise CheckpointError(f"{damaged} (negative or non-finite gains); retrain the model.")
        if bins.numel() and (int(bins.min()) < -1 or int(bins.max()) >= num_bins):
            raise CheckpointError(f"{damaged} (bins off the angle grid); retrain the model.")
        index = pd.MultiIndex.from_arrays([cells.numpy(), grids.numpy()], names=["cell_id", "grid_id"])
        scores = {str(k): float(v) for k, v in dict(state.get("scores") or {}).items()}
        weight = state.get("weight")
        if weight is not None:
            weight = torch.as_tensor(weight).float() if isinstance(weight, torch.Tensor) else None
            if weight is None or weight.shape != (len(index),) or not bool(((weight > 0) & (weight <= 1)).all()):
                raise CheckpointError(f"{damaged} (its weights are not one in (0, 1] per pair); retrain the model.")
        return cls(index, bins, gains, scores, weight)
