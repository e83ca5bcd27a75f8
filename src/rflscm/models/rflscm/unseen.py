"""Anchors for pairs without reports, interpolated from the same cell's anchors at nearby grids (issue 28).

A training pair's anchor (:mod:`.corrections`) is the median error the field leaves on its own reported round-1
beams after the cell's level.  At a grid with no report for a cell (an unseen grid, or a cell the grid did not
report) there is no anchor, and the field predicts with the cell's level alone.  The field's error is spatially
correlated, so the anchors of the cell at nearby grids say what it is there: :class:`AnchorField` predicts it as a
Gaussian-kernel average over the ``NEIGHBOURS`` nearest anchored grids of the same cell, shrunk toward 0 (the
level alone) by a prior weight,

    â(q) = Σ_i w_i a_i / (w_0 + Σ_i w_i),    w_i = exp(−d_i² / 2 L²),

so that a pair far from every anchored grid keeps the level alone.  The length ``L`` and the prior weight ``w_0``
are chosen by leave-one-out over the anchored pairs themselves (each predicted from the others of its cell, the
error weighted by its number of reported beams); "no interpolation" (â = 0) is always a candidate, so the
choice cannot do worse than the level alone on the anchored pairs.  Round 2 and held-out grids are never read.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from scipy.spatial import cKDTree

from rflscm.errors import CheckpointError

NEIGHBOURS = 8
"""Anchored grids of the same cell that an interpolated anchor averages over (the nearest)."""
LENGTHS_M = (5.0, 10.0, 20.0, 40.0, 80.0, 160.0)
"""Candidate kernel lengths L [m]."""
PRIOR_WEIGHTS = (0.1, 0.3, 1.0, 3.0)
"""Candidate prior weights w_0 (in units of one neighbour at distance 0)."""


@dataclass
class AnchorField:
    """The anchored pairs (``cell_ids [P]``, grid positions ``xyz [P, 3]`` [m], ``anchor_db [P]``) and the chosen
    kernel length ``length_m`` and prior weight ``prior_weight``; ``scores``: the leave-one-out MAE [dB] of each
    candidate ``(L, w_0)`` (and ``(0, 0)``: no interpolation).  ``length_m`` 0 is the interpolation switched off
    by the choice (no pairs kept; every prediction 0)."""

    cell_ids: np.ndarray
    xyz: np.ndarray
    anchor_db: np.ndarray
    length_m: float
    prior_weight: float
    scores: dict[tuple[float, float], float] = field(default_factory=dict)
    _trees: dict[int, tuple[cKDTree, np.ndarray]] = field(default_factory=dict, repr=False, compare=False)

    def predict(self, cell_ids: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """Interpolated anchors [dB] ``[N]`` of pairs (``cell_ids [N]``, positions ``xyz [N, 3]`` [m]); 0 for a cell
        without anchored grids."""
        cells = np.asarray(cell_ids, np.int64).reshape(-1)
        where = np.asarray(xyz, np.float64).reshape(-1, 3)
        out = np.zeros(len(cells))
        if self.length_m <= 0.0:
            return out
        for cell in np.unique(cells):
            tree = self._tree(int(cell))
            if tree is None:
                continue
            rows = np.nonzero(cells == cell)[0]
            dist, idx = _query(tree[0], where[rows], NEIGHBOURS)
            out[rows] = _kernel(dist, tree[1][np.minimum(idx, len(tree[1]) - 1)], self.length_m, self.prior_weight)
        return out

    def _tree(self, cell: int) -> tuple[cKDTree, np.ndarray] | None:
        if cell not in self._trees:
            mine = self.cell_ids == cell
            if not mine.any():
                return None
            self._trees[cell] = (cKDTree(self.xyz[mine]), self.anchor_db[mine])
        return self._trees[cell]

    def to_state(self) -> dict[str, torch.Tensor]:
        """Tensors only (a checkpoint loads it with ``weights_only=True``)."""
        return {
            "cell_id": torch.as_tensor(self.cell_ids.astype(np.int64)),
            "xyz": torch.as_tensor(self.xyz.astype(np.float64)),
            "anchor_db": torch.as_tensor(self.anchor_db.astype(np.float64)),
            "kernel": torch.tensor([self.length_m, self.prior_weight], dtype=torch.float64),
        }

    @classmethod
    def from_state(cls, state: object) -> AnchorField | None:
        """Inverse of :meth:`to_state` (None: none was fitted); damaged entries are a one-line
        :class:`CheckpointError`."""
        if state is None:
            return None
        keys = ("cell_id", "xyz", "anchor_db", "kernel")
        if not isinstance(state, dict) or any(k not in state for k in keys):
            raise CheckpointError(
                "the checkpoint's unseen-grid anchors are damaged (expected cell_id, xyz, anchor_db, kernel)."
            )
        cells = torch.as_tensor(state["cell_id"]).reshape(-1).numpy().astype(np.int64)
        xyz = torch.as_tensor(state["xyz"]).double().numpy()
        anchor = torch.as_tensor(state["anchor_db"]).reshape(-1).double().numpy()
        kernel = torch.as_tensor(state["kernel"]).reshape(-1).double().numpy()
        if xyz.shape != (len(cells), 3) or len(anchor) != len(cells) or len(kernel) != 2:
            raise CheckpointError("the checkpoint's unseen-grid anchors are damaged (columns of different lengths).")
        if not (np.isfinite(xyz).all() and np.isfinite(anchor).all() and np.isfinite(kernel).all()) or kernel.min() < 0:
            raise CheckpointError(
                "the checkpoint's unseen-grid anchors are damaged (non-finite values); retrain the model."
            )
        return cls(cells, xyz, anchor, float(kernel[0]), float(kernel[1]))


def fit_anchor_field(
    cell_ids: np.ndarray, xyz: np.ndarray, anchor_db: np.ndarray, beams: np.ndarray
) -> AnchorField:
    """The :class:`AnchorField` of the anchored pairs (``cell_ids [P]``, ``xyz [P, 3]`` [m], ``anchor_db [P]``, each
    with ``beams [P]`` reported training beams), ``(L, w_0)`` chosen by leave-one-out (see the module's docstring)
    with every candidate's leave-one-out MAE [dB] (``(0.0, 0.0)``: the level alone); switched off (``length_m`` 0,
    no pairs kept) when no candidate beats the level alone."""
    cells = np.asarray(cell_ids, np.int64).reshape(-1)
    where = np.asarray(xyz, np.float64).reshape(-1, 3)
    anchor = np.asarray(anchor_db, np.float64).reshape(-1)
    weight = np.asarray(beams, np.float64).reshape(-1)
    dists, values, truth, weights = [], [], [], []
    for cell in np.unique(cells):
        rows = np.nonzero(cells == cell)[0]
        if len(rows) < 2:
            continue
        dist, idx = _query(cKDTree(where[rows]), where[rows], NEIGHBOURS + 1)
        dist, idx = dist[:, 1:], idx[:, 1:]  # the nearest is the pair itself
        dists.append(dist)
        values.append(anchor[rows][np.minimum(idx, len(rows) - 1)])
        truth.append(anchor[rows])
        weights.append(weight[rows])
    scores: dict[tuple[float, float], float] = {}
    if not dists:
        return _off(scores)
    dist, value, a, w = (np.concatenate(x) for x in (dists, values, truth, weights))
    total = max(float(w.sum()), 1e-12)
    scores[(0.0, 0.0)] = float((w * np.abs(a)).sum() / total)
    for length in LENGTHS_M:
        for prior in PRIOR_WEIGHTS:
            scores[(length, prior)] = float((w * np.abs(a - _kernel(dist, value, length, prior))).sum() / total)
    best = min(scores, key=lambda k: (scores[k], k))
    if best == (0.0, 0.0):
        return _off(scores)
    return AnchorField(cells, where, anchor, best[0], best[1], scores)


def _off(scores: dict[tuple[float, float], float]) -> AnchorField:
    return AnchorField(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0), 0.0, 0.0, scores)


def _query(tree: cKDTree, points: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Distances and indices ``[n, k]`` of the ``k`` nearest points (∞ and an out-of-range index past the tree's
    size)."""
    dist, idx = tree.query(points, k=k)
    return np.asarray(dist).reshape(len(points), k), np.asarray(idx).reshape(len(points), k)


def _kernel(dist: np.ndarray, value: np.ndarray, length: float, prior: float) -> np.ndarray:
    """Σ w v / (w_0 + Σ w) per row with w = exp(−d² / 2 L²) (w = 0 at d = ∞)."""
    w = np.exp(-0.5 * np.square(np.where(np.isfinite(dist), dist, math.inf) / length))
    return (w * np.where(np.isfinite(dist), value, 0.0)).sum(1) / (prior + w.sum(1))
