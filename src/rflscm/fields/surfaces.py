"""Surface orientation from the point cloud: where walls face, for the decoder's specular cue.

A specular reflection at a wall sample p sends the ray's energy towards the grid only when the
half-vector h between the direction to the grid and −ω is parallel to the wall's normal n(p).  The
decoder can learn n from its features only slowly; the scan already knows it.  Per point, the
normal is the least-variance axis of its k nearest neighbours (local PCA); the sign-free outer
products n nᵀ are averaged on a voxel grid (a structure tensor T, trace 1 where points exist, 0
elsewhere) and interpolated at the samples.  The *specularity* s = hᵀ T h ∈ [0, 1] is 1 for a
mirror-like configuration on a clean plane and cos²(angle between h and n) in general.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from scipy.spatial import cKDTree
from torch import nn

_PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
"""Order of the six unique components of a symmetric 3 × 3 tensor."""


def point_normals(points: np.ndarray, neighbours: int = 12) -> np.ndarray:
    """Unit normals ``[N, 3]`` (sign arbitrary) from the PCA of each point's ``neighbours`` nearest points."""
    pts = np.asarray(points, np.float64)
    k = min(neighbours, len(pts))
    if k < 3:
        raise ValueError(f"need at least 3 points for normals (got {len(pts)}).")
    _, idx = cKDTree(pts).query(pts, k=k, workers=-1)
    local = pts[idx] - pts[idx].mean(axis=1, keepdims=True)  # [N, k, 3]
    cov = np.einsum("nki,nkj->nij", local, local)
    _, vectors = np.linalg.eigh(cov)  # ascending eigenvalues
    return vectors[:, :, 0]


def structure_grid(
    points: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    shape: tuple[int, int, int],
    neighbours: int = 12,
    max_points: int = 400_000,
    seed: int = 0,
) -> np.ndarray:
    """Mean n nᵀ per voxel of the grid spanning ``lo … hi`` with ``shape`` points: ``[nx, ny, nz, 6]``
    (components in :data:`_PAIRS` order, trace 1 where any point falls, 0 elsewhere).  Clouds larger
    than ``max_points`` are subsampled (deterministically with ``seed``) before the PCA."""
    pts = np.asarray(points, np.float64)
    if len(pts) > max_points:
        pts = pts[np.random.default_rng(seed).choice(len(pts), max_points, replace=False)]
    shape_arr = np.asarray(shape)
    out = np.zeros((*shape, 6), np.float64)
    if len(pts) < 3:
        return out.astype(np.float32)
    normals = point_normals(pts, neighbours)
    step = (np.asarray(hi, np.float64) - np.asarray(lo, np.float64)) / np.maximum(shape_arr - 1, 1)
    idx = np.rint((pts - lo) / step).astype(np.int64)
    inside = np.all((idx >= 0) & (idx < shape_arr), axis=1)
    flat = np.ravel_multi_index(tuple(idx[inside].T), shape)
    comps = np.stack([normals[inside, i] * normals[inside, j] for i, j in _PAIRS], axis=1)
    sums = np.stack([np.bincount(flat, comps[:, c], minlength=int(np.prod(shape))) for c in range(6)], axis=1)
    trace = sums[:, :3].sum(1, keepdims=True)
    out = np.where(trace > 0, sums / np.maximum(trace, 1e-12), 0.0).reshape(*shape, 6)
    return out.astype(np.float32)


class SurfaceOrientation(nn.Module):
    """T(p) ``[S, 6]`` interpolated from a :func:`structure_grid` (buffers only)."""

    grid: torch.Tensor
    box_lo: torch.Tensor
    box_hi: torch.Tensor

    def __init__(self, grid: torch.Tensor, box_lo: torch.Tensor, box_hi: torch.Tensor) -> None:
        super().__init__()
        g = torch.as_tensor(grid, dtype=torch.float32)  # [nx, ny, nz, 6]
        self.register_buffer("grid", g.permute(3, 2, 1, 0)[None].contiguous())  # [1, 6, nz, ny, nx]
        self.register_buffer("box_lo", torch.as_tensor(box_lo, dtype=torch.float32))
        self.register_buffer("box_hi", torch.as_tensor(box_hi, dtype=torch.float32))

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        u = 2.0 * (points.to(self.box_lo.dtype) - self.box_lo) / (self.box_hi - self.box_lo) - 1.0
        out = F.grid_sample(
            self.grid, u.view(1, -1, 1, 1, 3), mode="bilinear", padding_mode="zeros", align_corners=True
        )
        return out.view(6, -1).T

    def grid_numpy(self) -> np.ndarray:
        """The grid as :func:`structure_grid` returns it (for checkpoints)."""
        return self.grid[0].permute(3, 2, 1, 0).cpu().numpy()


def specularity(tensor6: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """s = hᵀ T h ``[J]`` for structure tensors ``[J, 6]`` and unit vectors ``h [J, 3]``."""
    x, y, z = h.unbind(-1)
    t = tensor6.unbind(-1)
    return t[0] * x * x + t[1] * y * y + t[2] * z * z + 2.0 * (t[3] * x * y + t[4] * x * z + t[5] * y * z)
