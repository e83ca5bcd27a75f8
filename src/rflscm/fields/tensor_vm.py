"""TensoRF vector-matrix (VM) tensor over the scene box (paper §IV-A, eqs. (20)–(21)).

𝒢 = Σ_{r=1}^{R} ( v_r^X ∘ M_r^{YZ} ∘ b¹ + v_r^Y ∘ M_r^{XZ} ∘ b² + v_r^Z ∘ M_r^{XY} ∘ b³ )

with a vector per axis, a matrix per orthogonal plane and a learnable basis
mapping to the D output channels.  The paper's form has one basis vector per mode
b¹, b², b³ ∈ ℝᴰ; the model uses two variants of it.  ``basis="per_component"``
gives every rank-1 component its own basis vector (TensoRF's appearance basis
matrix), which is strictly more expressive for wide latent features.
``basis="per_channel"`` gives every output channel its own R components per mode
and its own per-mode scalars b^m_c (the paper's form with a diagonal basis):
channels with very different gradient scales (e.g. a loss and a phase-like
index) then never share a factor, so Adam moves each at its own pace.  Look-ups interpolate with
``torch.nn.functional.grid_sample``: bilinear on the planes, linear on the lines
(``align_corners=True``: grid point i of an axis sits at lo + i·(hi − lo)/(res − 1)).
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from rflscm.errors import ConfigError

# mode m: the line runs along axis LINE_AXES[m], the plane spans PLANE_AXES[m] (grid_sample x, y)
LINE_AXES = (0, 1, 2)
PLANE_AXES = ((1, 2), (0, 2), (0, 1))


def resolution_for(box_lo: torch.Tensor, box_hi: torch.Tensor, voxel_m: float, max_res: int) -> tuple[int, int, int]:
    """Grid points per axis so that the spacing is about ``voxel_m`` [m], capped at ``max_res``."""
    extent = (box_hi - box_lo).tolist()
    return tuple(int(min(max(round(e / voxel_m) + 1, 2), max_res)) for e in extent)  # type: ignore[return-value]


class TensorVM(nn.Module):
    """A D-channel field ``[num_points, 3] → [num_points, D]`` stored as a VM decomposition.

    Args:
        box_lo, box_hi: the scene box ``[3]`` [m]; points outside read the border values.
        resolution: grid points per axis (X, Y, Z).
        rank: number of rank-1 components per mode (R₁ or R₂ in the paper).
        out_dim: output channels D.
        basis: ``"per_component"`` (ℝ^{3R×D}) or ``"per_channel"`` (R components per mode and channel,
            b^m_c ∈ ℝ, initialised to 1).  (The paper's ``per_mode`` basis, b^m ∈ ℝᴰ, left with issue 11.)
        init_scale: standard deviation of the initial vector and matrix entries.
    """

    box_lo: torch.Tensor
    box_hi: torch.Tensor

    def __init__(
        self,
        box_lo: torch.Tensor,
        box_hi: torch.Tensor,
        resolution: tuple[int, int, int],
        rank: int,
        out_dim: int,
        basis: Literal["per_component", "per_channel"],
        init_scale: float = 0.1,
    ) -> None:
        super().__init__()
        if rank < 1 or out_dim < 1 or min(resolution) < 2:
            raise ConfigError(
                f"a VM tensor needs rank ≥ 1, D ≥ 1 and ≥ 2 points per axis (got {rank}, {out_dim}, {resolution})."
            )
        self.register_buffer("box_lo", torch.as_tensor(box_lo, dtype=torch.float32).clone())
        self.register_buffer("box_hi", torch.as_tensor(box_hi, dtype=torch.float32).clone())
        self.rank, self.out_dim, self.basis_kind = rank, out_dim, basis
        self.resolution = tuple(int(r) for r in resolution)
        res = self.resolution
        rank = rank * out_dim if basis == "per_channel" else rank  # stored components per mode
        self.lines = nn.ParameterList([nn.Parameter(init_scale * torch.randn(1, rank, res[a], 1)) for a in LINE_AXES])
        # plane [1, R, H, W]: H indexes the plane's second axis, W its first (grid_sample's y, x)
        self.planes = nn.ParameterList(
            [nn.Parameter(init_scale * torch.randn(1, rank, res[v], res[u])) for u, v in PLANE_AXES]
        )
        if basis == "per_channel":
            self.basis = nn.Parameter(torch.ones(3, out_dim))
        else:
            num_in = 3 * rank
            self.basis = nn.Parameter(torch.randn(num_in, out_dim) / num_in**0.5)

    def normalise(self, points: torch.Tensor) -> torch.Tensor:
        """World points ``[S, 3]`` [m] → box coordinates in [−1, 1]."""
        return 2.0 * (points - self.box_lo) / (self.box_hi - self.box_lo) - 1.0

    def components(self, points: torch.Tensor) -> torch.Tensor:
        """Per-mode rank-1 products ``[S, 3, R]`` at world points ``[S, 3]``."""
        u = self.normalise(points.to(self.box_lo.dtype))
        out = []
        for m in range(3):
            a, (pu, pv) = LINE_AXES[m], PLANE_AXES[m]
            line_grid = torch.stack((torch.zeros_like(u[:, a]), u[:, a]), dim=-1)  # [S, 2]
            plane_grid = torch.stack((u[:, pu], u[:, pv]), dim=-1)
            line = _sample(self.lines[m], line_grid)  # [S, R]
            plane = _sample(self.planes[m], plane_grid)
            out.append(line * plane)
        return torch.stack(out, dim=1)

    def forward(self, points: torch.Tensor) -> torch.Tensor:
        """Field values ``[S, D]`` at world points ``[S, 3]`` [m]."""
        comp = self.components(points)  # [S, 3, R]  (R·D for per_channel)
        if self.basis_kind == "per_channel":
            per_channel = comp.view(comp.shape[0], 3, self.out_dim, self.rank).sum(-1)  # [S, 3, D]
            return (per_channel * self.basis).sum(1)
        return comp.flatten(1) @ self.basis

    @torch.no_grad()
    def upsample(self, new_resolution: tuple[int, int, int]) -> None:
        """Resample every factor to ``new_resolution`` (linear / bilinear, corners aligned).

        The represented function is unchanged at every old grid point that is also a new grid
        point (e.g. ``new = 2·old − 1``) and interpolated elsewhere.  Parameters are replaced, so
        an optimizer must be rebuilt afterwards.
        """
        new = tuple(int(r) for r in new_resolution)
        for m in range(3):
            a, (pu, pv) = LINE_AXES[m], PLANE_AXES[m]
            line = F.interpolate(self.lines[m].data, size=(new[a], 1), mode="bilinear", align_corners=True)
            plane = F.interpolate(self.planes[m].data, size=(new[pv], new[pu]), mode="bilinear", align_corners=True)
            self.lines[m] = nn.Parameter(line.contiguous())
            self.planes[m] = nn.Parameter(plane.contiguous())
        self.resolution = new

    def grid_points(self) -> torch.Tensor:
        """World coordinates ``[X, Y, Z, 3]`` of every grid point."""
        axes = [torch.linspace(float(lo), float(hi), r) for lo, hi, r in zip(self.box_lo, self.box_hi, self.resolution)]
        return torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).to(self.box_lo.device)


def _sample(factor: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """Interpolate ``factor [1, R, H, W]`` at ``grid [S, 2]`` (x → W, y → H, in [−1, 1]) → ``[S, R]``."""
    out = F.grid_sample(factor, grid.view(1, -1, 1, 2), mode="bilinear", padding_mode="border", align_corners=True)
    return out[0, :, :, 0].T
