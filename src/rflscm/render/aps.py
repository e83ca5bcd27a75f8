"""Rendering the APS (paper eqs. (1)–(2), (18)): no parameters.

s̃(ω_n) = Σ_q (Π_{q̃≤q} δ̃_q̃) R̃_q ,   x̃(ω_n) = |s̃(ω_n)|²

Samples come flat, ray after ray, in order along each ray (``ray [S]`` non-decreasing).  The
cumulative product is a segmented cumulative sum of log δ̃, accumulated in float64 (stable,
cheap gradients, no padding).  Samples left out of a ray are inert (δ̃ = 1, R̃ = 0), so a
ray's stored samples give exactly the full sum.
"""

from __future__ import annotations

from collections.abc import Callable

import torch


def segment_starts(ray: torch.Tensor) -> torch.Tensor:
    """Index ``[S]`` of the first sample of each sample's ray (``ray [S]`` non-decreasing)."""
    first = torch.ones_like(ray, dtype=torch.bool)
    first[1:] = ray[1:] != ray[:-1]
    pos = torch.arange(ray.numel(), device=ray.device)
    return torch.cummax(torch.where(first, pos, torch.zeros_like(pos)), 0).values


def segment_cumsum(values: torch.Tensor, ray: torch.Tensor) -> torch.Tensor:
    """Cumulative sum (inclusive) of complex ``values [S]`` within each ray, in float64, cast back."""
    v = torch.view_as_real(values.to(torch.complex128))  # [S, 2]
    total = torch.cumsum(v, 0)
    start = segment_starts(ray)
    out = total - total[start] + v[start]
    return torch.view_as_complex(out.contiguous()).to(values.dtype)


def transmittance(log_delta: torch.Tensor, ray: torch.Tensor, max_log_gain: float | None = 0.0) -> torch.Tensor:
    """Cumulative transmittance Π_{q̃≤q} δ̃ ``[S]`` (complex; as in the paper, a voxel's own attenuation applies
    to its radiance) from log δ̃ ``[S]`` of samples of rays ``ray [S]``.

    Args:
        max_log_gain: passivity guard: the cumulative log-magnitude is capped at this value
            (0 → |Π δ̃| ≤ 1), since single FDAM factors can exceed 1 (see :mod:`rflscm.fields.fdam`)
            and the Φ-weighting breaks the entry/exit compensation; ``None`` disables it.
    """
    cum = segment_cumsum(log_delta, ray)
    if max_log_gain is None:
        return torch.exp(cum)
    return torch.exp(torch.complex(cum.real.clamp(max=max_log_gain), cum.imag))


def accumulate_power(contrib: torch.Tensor, target: torch.Tensor, num_targets: int) -> torch.Tensor:
    """x̃ ``[num_targets]`` from complex ``contrib [J]`` of targets ``target [J]``: |Σ contributions|², the
    coherent sum of the paper's eq. (18)."""
    s = torch.zeros(num_targets, dtype=contrib.dtype, device=contrib.device).index_add(0, target, contrib)
    return s.real.square() + s.imag.square()


def render_power(
    log_delta: torch.Tensor,
    radiance: torch.Tensor,
    ray: torch.Tensor,
    num_rays: int,
    max_log_gain: float | None = 0.0,
) -> torch.Tensor:
    """x̃ = |Σ_q (Π δ̃) R̃_q|² ``[num_rays]`` from log δ̃ and R̃ (complex ``[S]``) of samples of rays ``ray [S]``."""
    contrib = transmittance(log_delta, ray, max_log_gain) * radiance
    return accumulate_power(contrib, ray, num_rays)


def chunk_bounds(costs: torch.Tensor, budget: int) -> list[tuple[int, int]]:
    """Split items with ``costs [n]`` (e.g. samples per ray) into consecutive chunks of total cost ≤ ``budget``
    (an item costlier than the budget gets a chunk of its own)."""
    bounds, start, n = [], 0, costs.numel()
    cum = torch.cumsum(costs.to(torch.int64), 0)
    while start < n:
        base = int(cum[start - 1]) if start else 0
        stop = int(torch.searchsorted(cum, base + budget, right=True))
        stop = max(stop, start + 1)
        bounds.append((start, stop))
        start = stop
    return bounds


def chunked(fn: Callable[[int, int], torch.Tensor], bounds: list[tuple[int, int]]) -> torch.Tensor:
    """``torch.cat([fn(a, b) for a, b in bounds])``: memory-bounded evaluation, e.g. for inference."""
    outs = [fn(a, b) for a, b in bounds]
    return torch.cat(outs) if outs else torch.empty(0)
