"""A left-over pair's APS borrowed from the nearest pair of its cell that the pass rendered (issue 29).

Within a budget the pass after training (:mod:`~rflscm.models.rflscm.corrections`) renders and corrects as many
training pairs as fit; the others are answered without a render of their own: by WNOMP's APS of their reports
(:mod:`.fallback`), or, here, by the field's APS at the nearest grid of the same cell that the pass rendered, shifted
by the pair's own anchor (the mean error left on its own round-1 reports after the cell's level).  Grids a few
metres apart see their cell through the same streets, so the neighbour's angular shape is close to the pair's own,
and the pair's reports pin its level, which a field trained briefly gets wrong first (the anchor's reason).  It costs
a nearest-neighbour query and the borrowed APS's predicted reports, no render; the pass chooses it for the pairs it
leaves where it predicts held-aside reports better than the field's level and than WNOMP.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from scipy.spatial import cKDTree

from rflscm.models.pairs import PairData
from rflscm.models.rflscm.anchors import report_mean
from rflscm.models.rflscm.fallback import predicted_reports


def nearest_of_cell(data: PairData, sources: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """``[T]`` for each training pair of ``targets``, the position in ``sources`` (training pairs) of the pair of the
    same cell whose grid is nearest, never the target itself; −1 where its cell has no other source."""
    cell_of = data.cell_index.cpu().numpy()
    xyz = data.grid_xyz.cpu().double().numpy()
    src, dst = sources.cpu().numpy(), targets.cpu().numpy()
    out = np.full(len(dst), -1, dtype=np.int64)
    for cell in np.unique(cell_of[dst]):
        mine = np.flatnonzero(cell_of[src] == cell)
        want = np.flatnonzero(cell_of[dst] == cell)
        if not len(mine) or not len(want):
            continue
        k = min(2, len(mine))
        _, near = cKDTree(xyz[src[mine]]).query(xyz[dst[want]], k=k)
        near = np.asarray(near).reshape(len(want), k)
        first = mine[near[:, 0]]
        if k == 2:  # a target that is a source itself borrows from its nearest other
            first = np.where(src[first] == dst[want], mine[near[:, 1]], first)
        elif len(mine) == 1:
            first = np.where(src[first] == dst[want], -1, first)
        out[want] = first
    return torch.as_tensor(out, device=targets.device)


def borrowed_reports(
    columns: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    data: PairData,
    targets: torch.Tensor,
    bins: torch.Tensor,
    values: torch.Tensor,
) -> torch.Tensor:
    """``[T, M]`` (normalised) the reports of training pairs ``targets`` predicted through their own cell's columns from
    the borrowed sparse APS ``(bins, values) [T, K]``."""
    return predicted_reports(columns, data.cell_index[targets], bins.long(), values)


def own_anchor(
    measured: torch.Tensor, predicted: torch.Tensor, mask: torch.Tensor, level_db: torch.Tensor
) -> torch.Tensor:
    """``[T]`` [dB] each pair's anchor: the mean of (measured − predicted) [dB] less its ``level_db [T, M]`` over its
    ``mask``-ed reports (0 where it has none; :func:`~rflscm.models.rflscm.anchors.report_mean`)."""
    resid = 10.0 * torch.log10(measured / predicted.clamp_min(1e-30)) - level_db
    return report_mean(resid, mask)
