"""Ray sampling (paper eq. (9)): p_{n,q} = p_BS + q Δr ω_n, q = 0 … Q−1.  No parameters.

Rays are stored sparsely: a :class:`RaySamples` keeps, per ray, only the samples that can
matter (Φ > threshold, plus one neighbour on each side so that FDAM's Γ_q, Γ_{q+1} see the
true neighbouring media).  Samples with Φ = 0 have δ̃ = 1 and R̃ = 0 exactly, so dropping them
changes nothing (empty-space skipping, SPEC §3 compute budget).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch


def num_samples_for(box_lo: torch.Tensor, box_hi: torch.Tensor, origins: torch.Tensor, step_m: float) -> int:
    """Q such that every ray from any origin ``[C, 3]`` reaches the farthest corner of the box."""
    corners = torch.stack(torch.meshgrid(*[torch.stack((lo, hi)) for lo, hi in zip(box_lo, box_hi)], indexing="ij"), -1)
    reach = torch.cdist(origins.double(), corners.reshape(-1, 3).double()).max()
    return int(math.ceil(float(reach) / step_m)) + 1


def ray_points(
    origins: torch.Tensor, directions: torch.Tensor, sample_index: torch.Tensor, step_m: float
) -> torch.Tensor:
    """Positions ``[..., 3]`` [m] of samples ``sample_index [...]`` on rays ``origins, directions [..., 3]``."""
    return origins + (sample_index.to(directions.dtype) * step_m)[..., None] * directions


@dataclass
class RaySamples:
    """The stored samples of a set of rays, CSR-style (ray r owns entries offsets[r] … offsets[r+1]−1).

    Attributes:
        offsets: int64 ``[num_rays + 1]``.
        index: int32 ``[nnz]`` sample index q along the ray, ascending within a ray.
        phi: float32 ``[nnz]`` point-cloud prior Φ of the sample (0 for the neighbours kept for FDAM).
    """

    offsets: torch.Tensor
    index: torch.Tensor
    phi: torch.Tensor

    @property
    def num_rays(self) -> int:
        return self.offsets.numel() - 1

    def live_counts(self) -> torch.Tensor:
        """Samples with Φ > 0 per ray ``[num_rays]`` (the decoder evaluations a ray costs per grid)."""
        counts = self.offsets[1:] - self.offsets[:-1]
        ray = torch.repeat_interleave(torch.arange(self.num_rays, device=self.offsets.device), counts)
        return torch.bincount(ray[self.phi > 0], minlength=self.num_rays)

    def spread(self, rays: torch.Tensor, num_rays: int) -> RaySamples:
        """These rays as rays ``rays [num_rays_here]`` (ascending) of a set of ``num_rays``, the others empty."""
        counts = torch.zeros(num_rays, dtype=self.offsets.dtype)
        counts[rays.cpu()] = (self.offsets[1:] - self.offsets[:-1]).cpu()
        offsets = torch.cat((counts.new_zeros(1), torch.cumsum(counts, 0))).to(self.offsets.device)
        return RaySamples(offsets, self.index, self.phi)

    def to(self, device: torch.device | str) -> RaySamples:
        return RaySamples(self.offsets.to(device), self.index.to(device), self.phi.to(device))

    @staticmethod
    def concat(parts: list[RaySamples]) -> RaySamples:
        """Rays of ``parts`` one after another."""
        shifts = torch.cumsum(torch.tensor([0] + [p.index.numel() for p in parts[:-1]]), 0)
        offsets = [parts[0].offsets[:1]] + [p.offsets[1:] + int(s) for p, s in zip(parts, shifts)]
        return RaySamples(torch.cat(offsets), torch.cat([p.index for p in parts]), torch.cat([p.phi for p in parts]))


def select_samples(phi: torch.Tensor, threshold: float = 0.0, halo: int = 1) -> RaySamples:
    """Keep the samples of rays ``phi [num_rays, Q]`` with Φ > ``threshold``, plus ``halo`` neighbours."""
    active = phi > threshold
    keep = active.clone()
    for shift in range(1, halo + 1):
        keep[:, shift:] |= active[:, :-shift]
        keep[:, :-shift] |= active[:, shift:]
    ray, index = keep.nonzero(as_tuple=True)  # row-major: by ray, then q ascending
    counts = torch.bincount(ray, minlength=phi.shape[0])
    offsets = torch.cat((counts.new_zeros(1), torch.cumsum(counts, 0)))
    value = torch.where(active[ray, index], phi[ray, index], torch.zeros_like(phi[ray, index]))
    return RaySamples(offsets, index.to(torch.int32), value.to(torch.float32))


@dataclass
class PackedSamples:
    """Stored samples of a batch of rays, flat: ray after ray, in order along each ray."""

    ray: torch.Tensor  # int64 [S] which batch ray
    index: torch.Tensor  # int64 [S] sample index q along the ray
    phi: torch.Tensor  # float32 [S]
    first: torch.Tensor  # bool [S] first stored sample of its ray
    last: torch.Tensor  # bool [S] last stored sample of its ray
    num_rays: int


def gather_samples(samples: RaySamples, rays: torch.Tensor) -> PackedSamples:
    """The stored samples of rays ``rays [B]`` (indices into ``samples``), vectorised."""
    starts = samples.offsets[rays]
    counts = samples.offsets[rays + 1] - starts
    ray = torch.repeat_interleave(torch.arange(rays.numel(), device=rays.device), counts)
    first_pos = torch.cumsum(counts, 0) - counts
    slot = torch.arange(ray.numel(), device=rays.device) - first_pos[ray]
    src = starts[ray] + slot
    return PackedSamples(
        ray, samples.index[src].long(), samples.phi[src], slot == 0, slot == counts[ray] - 1, rays.numel()
    )


def join_queries(query_ray: torch.Tensor, sample_ray: torch.Tensor, num_rays: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Pair every query with every sample of its ray.

    A query asks for one ray seen from one grid; several queries may share a ray (the fields
    along a ray do not depend on the grid, the decoder does).  ``sample_ray [L]`` must be
    non-decreasing.  Returns ``(query [J], sample [J])`` index pairs, grouped by query.
    """
    counts = torch.bincount(sample_ray, minlength=num_rays)
    start = torch.cumsum(counts, 0) - counts
    per_query = counts[query_ray]
    query = torch.repeat_interleave(torch.arange(query_ray.numel(), device=query_ray.device), per_query)
    first = torch.cumsum(per_query, 0) - per_query
    sample = start[query_ray][query] + torch.arange(query.numel(), device=query.device) - first[query]
    return query, sample


def build_ray_samples(
    origin: torch.Tensor,
    directions: torch.Tensor,
    num_samples: int,
    step_m: float,
    phi_fn: Callable[[torch.Tensor], torch.Tensor] | None,
    threshold: float = 0.0,
    max_points: int = 2_000_000,
) -> RaySamples:
    """Evaluate Φ on every sample of rays from ``origin [3]`` along ``directions [N, 3]`` and keep what
    matters (:func:`select_samples`); ``phi_fn=None`` means no prior (Φ = 1, every sample kept).
    Works in chunks of about ``max_points`` samples."""
    if phi_fn is None:
        n = directions.shape[0]
        offsets = torch.arange(n + 1, dtype=torch.int64) * num_samples
        index = torch.arange(num_samples, dtype=torch.int32).repeat(n)
        return RaySamples(offsets, index, torch.ones(n * num_samples))
    q = torch.arange(num_samples, device=directions.device)
    chunk = max(1, max_points // num_samples)
    parts = []
    for start in range(0, directions.shape[0], chunk):
        pts = ray_points(origin, directions[start : start + chunk, None, :], q, step_m)  # [n, Q, 3]
        phi = phi_fn(pts.reshape(-1, 3)).view(pts.shape[:2])
        parts.append(select_samples(phi.cpu(), threshold).to("cpu"))
    return RaySamples.concat(parts)
