"""Point-cloud prior Φ (paper §III-D, eqs. (14)–(17)).

D(p) = #{a ∈ cloud : ‖a − p‖ ≤ Δr} is counted once on a voxel grid (each point adds to the grid
points within reach) and looked up by trilinear interpolation; Φ = 1 where D > D_th, else β·D; then R̃ = R·Φ and
δ̃ = δ^Φ = exp(Φ log δ).  Φ = 0 (no point within reach) makes a sample inert, which the
model uses to skip it entirely (empty-space skipping).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

FOLD_AT = 8_000_000
"""Stencil hits :func:`density_grid` holds before adding them to the grid (bounds its memory)."""


def grid_span(
    box_lo: np.ndarray, box_hi: np.ndarray, voxel_m: float
) -> tuple[np.ndarray, np.ndarray, tuple[int, int, int]]:
    """``(lo, hi, shape)`` of the regular grid with spacing ``voxel_m`` that starts at ``box_lo`` and covers
    ``box_hi`` (at least 2 points per axis): point (i, j, k) sits at ``lo + (i, j, k)·voxel_m``."""
    lo = np.asarray(box_lo, np.float64)
    shape = np.maximum(np.ceil((np.asarray(box_hi, np.float64) - lo) / voxel_m).astype(int) + 1, 2)
    nx, ny, nz = (int(n) for n in shape)
    return lo, lo + (shape - 1) * voxel_m, (nx, ny, nz)


def density_grid(
    points: np.ndarray, box_lo: np.ndarray, box_hi: np.ndarray, voxel_m: float, radius_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point counts within ``radius_m`` of every voxel-grid point of the box.

    Returns ``(density [nx, ny, nz] float32, lo [3], hi [3])``; grid point (i, j, k) sits at
    ``lo + (i, j, k)·voxel_m`` and ``hi = lo + (shape − 1)·voxel_m`` covers the box.  Each point adds
    one to the grid points of a small stencil around it that lie within ``radius_m`` (distances
    in float64), one stencil offset at a time: the same counts as a KD-tree ball query per grid point,
    at a fraction of the cost.
    """
    lo, hi, shape = grid_span(box_lo, box_hi, voxel_m)
    pts = np.asarray(points, np.float64)
    total = np.zeros(int(np.prod(shape)), np.float64)
    if len(pts):
        rel = (pts - lo) / voxel_m
        base = np.floor(rel).astype(np.int64)
        r2 = (radius_m / voxel_m) ** 2
        reach = int(math.ceil(radius_m / voxel_m))
        span = np.arange(-reach, reach + 2)
        offsets = np.stack(np.meshgrid(span, span, span, indexing="ij"), -1).reshape(-1, 3)
        nearest = np.where(offsets < 0, -offsets, np.maximum(offsets - 1, 0))  # least |rel − idx| per axis
        flats: list[np.ndarray] = []
        held = 0
        for offset in offsets[np.square(nearest).sum(1) <= r2]:
            idx = base + offset
            keep = np.all((idx >= 0) & (idx < shape), axis=1) & (np.square(rel - idx).sum(1) <= r2)
            flats.append(np.ravel_multi_index(tuple(idx[keep].T), shape))
            held += int(keep.sum())
            if held > FOLD_AT:  # bounded memory: fold what is held into the grid
                total += np.bincount(np.concatenate(flats), minlength=total.size)
                flats, held = [], 0
        if flats:
            total += np.bincount(np.concatenate(flats), minlength=total.size)
    return total.reshape(shape).astype(np.float32), lo, hi


class PointPrior(nn.Module):
    """Φ(p) from a precomputed density grid (buffers only, no parameters).

    Args:
        density: point counts ``[nx, ny, nz]`` on the grid spanning ``box_lo`` … ``box_hi``.
        threshold: D_th; Φ = 1 where the interpolated density exceeds it.
        beta: β ≪ 1; Φ = β·D below the threshold.
    """

    density_grid: torch.Tensor
    box_lo: torch.Tensor
    box_hi: torch.Tensor

    def __init__(
        self, density: torch.Tensor, box_lo: torch.Tensor, box_hi: torch.Tensor, threshold: float, beta: float
    ) -> None:
        super().__init__()
        grid = torch.as_tensor(density, dtype=torch.float32).permute(2, 1, 0)  # [nz, ny, nx] for grid_sample
        self.register_buffer("density_grid", grid[None, None].contiguous())
        self.register_buffer("box_lo", torch.as_tensor(box_lo, dtype=torch.float32))
        self.register_buffer("box_hi", torch.as_tensor(box_hi, dtype=torch.float32))
        self.threshold = float(threshold)
        self.beta = float(beta)

    @classmethod
    def from_points(
        cls,
        points: np.ndarray,
        box_lo: np.ndarray,
        box_hi: np.ndarray,
        voxel_m: float,
        radius_m: float,
        threshold: float,
        beta: float,
    ) -> PointPrior:
        """Count the cloud once on a ``voxel_m`` grid over the box (:func:`density_grid`)."""
        density, lo, hi = density_grid(points, box_lo, box_hi, voxel_m, radius_m)
        return cls(torch.from_numpy(density), torch.from_numpy(lo), torch.from_numpy(hi), threshold, beta)

    def density(self, points: torch.Tensor) -> torch.Tensor:
        """Interpolated D ``[S]`` at world points ``[S, 3]`` [m]; 0 outside the grid."""
        u = 2.0 * (points.to(self.box_lo.dtype) - self.box_lo) / (self.box_hi - self.box_lo) - 1.0
        out = F.grid_sample(
            self.density_grid, u.view(1, -1, 1, 1, 3), mode="bilinear", padding_mode="zeros", align_corners=True
        )
        return out.view(-1)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """Φ ``[S]`` at world points ``[S, 3]`` (paper eq. (15))."""
        return phi_of_density(self.density(points), self.threshold, self.beta)


def phi_of_density(density: torch.Tensor, threshold: float, beta: float) -> torch.Tensor:
    """Φ = 1 if D > D_th else β·D  (paper eq. (15))."""
    return torch.where(density > threshold, torch.ones_like(density), beta * density)


def modulate(phi: torch.Tensor, radiance: torch.Tensor, log_delta: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """R̃ = R·Φ and log δ̃ = Φ·log δ, i.e. δ̃ = δ^Φ (paper eqs. (16)–(17)); all ``[...]``."""
    return radiance * phi, log_delta * phi
