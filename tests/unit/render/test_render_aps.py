"""The APS integral: transmittance by log-space cumulative sums, |Σ|², chunking."""

from __future__ import annotations

import itertools
import math

import numpy as np
import torch

from rflscm.fields import PointPrior
from rflscm.geometry import AngleGrid
from rflscm.render import (
    build_ray_samples,
    chunk_bounds,
    chunked,
    gather_samples,
    render_power,
    segment_cumsum,
    transmittance,
)


def random_log_delta(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.complex(
        -torch.rand(n, generator=g, dtype=torch.float64), 6.0 * torch.randn(n, generator=g, dtype=torch.float64)
    )


def test_transmittance_is_the_cumulative_product_per_ray() -> None:
    log_delta = random_log_delta(9)
    ray = torch.tensor([0, 0, 0, 0, 2, 2, 3, 3, 3])
    t = transmittance(log_delta, ray, max_log_gain=None)  # Π_{q̃≤q}: a voxel's own δ̃ applies to it (paper)
    delta = torch.exp(log_delta)
    for seg in ([0, 1, 2, 3], [4, 5], [6, 7, 8]):
        assert torch.allclose(t[seg], torch.cumprod(delta[seg], 0), atol=1e-12)


def test_passivity_guard_caps_the_magnitude() -> None:
    log_delta = torch.tensor([0.3 + 1j, -0.1 + 0j, 0.5 + 0j, -2.0 + 0j], dtype=torch.complex128)
    ray = torch.zeros(4, dtype=torch.long)
    t = transmittance(log_delta, ray, max_log_gain=0.0)
    assert torch.allclose(t.abs(), torch.tensor([1.0, 1.0, 1.0, math.exp(-1.3)], dtype=torch.float64))
    assert torch.allclose(torch.angle(t[0]), torch.tensor(1.0, dtype=torch.float64))


def test_long_rays_keep_phase_precision_in_float32() -> None:
    n = 200_000  # many rays of 200 samples with ~290 rad per sample (k·d at 3.5 GHz, 4 m)
    log_delta = torch.full((n,), complex(-1e-4, -290.0), dtype=torch.complex64)
    ray = torch.arange(n) // 200
    cum = segment_cumsum(log_delta, ray)
    expected = torch.tensor((np.arange(n) % 200 + 1) * -290.0, dtype=torch.float32)
    assert torch.allclose(cum.imag, expected, atol=1e-2)


def test_render_power_matches_direct_sum() -> None:
    log_delta = random_log_delta(5, seed=3)
    radiance = torch.complex(torch.randn(5, dtype=torch.float64), torch.randn(5, dtype=torch.float64))
    ray = torch.tensor([0, 0, 0, 1, 1])
    x = render_power(log_delta, radiance, ray, 3, max_log_gain=None)
    delta = torch.exp(log_delta)
    s0 = delta[0] * radiance[0] + delta[0] * delta[1] * radiance[1] + delta[0] * delta[1] * delta[2] * radiance[2]
    s1 = delta[3] * radiance[3] + delta[3] * delta[4] * radiance[4]
    assert torch.allclose(x, torch.stack((s0.abs() ** 2, s1.abs() ** 2, torch.tensor(0.0, dtype=torch.float64))))


def test_single_scatterer_lands_in_its_bin() -> None:
    """A lone dense spot in free space renders power only in the angle bins looking at it."""
    grid = AngleGrid.full_sphere(19, 36)  # 10° steps
    site = torch.tensor([0.0, 0.0, 30.0])
    spot = torch.tensor([60.0, 35.0, 2.0])
    cloud = spot + 0.3 * torch.randn(200, 3)
    prior = PointPrior.from_points(
        cloud.numpy(),
        np.array([-100.0, -100.0, -10.0]),
        np.array([100.0, 100.0, 50.0]),
        voxel_m=2.0,
        radius_m=4.0,
        threshold=20.0,
        beta=0.01,
    )
    samples = build_ray_samples(site, grid.directions(), 60, 4.0, prior)
    packed = gather_samples(samples, torch.arange(grid.num_bins))
    live = packed.phi > 0
    x = render_power(
        torch.zeros(int(live.sum()), dtype=torch.complex64),
        packed.phi[live].to(torch.complex64),
        packed.ray[live],
        grid.num_bins,
    )
    expected = int(grid.bin_of_vectors((spot - site)[None] / (spot - site).norm())[0])
    assert int(x.argmax()) == expected
    assert float(x[expected]) > 0.3 * float(x.sum())


def test_chunk_bounds_respect_budget_and_cover_everything() -> None:
    costs = torch.tensor([3, 1, 4, 1, 5, 9, 2, 6])
    bounds = chunk_bounds(costs, 7)
    assert bounds[0][0] == 0 and bounds[-1][1] == 8
    assert all(b[1] == n[0] for b, n in itertools.pairwise(bounds))
    for a, b in bounds:
        assert costs[a:b].sum() <= 7 or b - a == 1
    out = chunked(lambda a, b: costs[a:b] * 2, bounds)
    assert torch.equal(out, costs * 2)


def test_coherent_sum_interferes() -> None:
    from rflscm.render import accumulate_power

    contrib = torch.tensor([1.0 + 0j, -1.0 + 0j, 0.5j, 2.0 + 0j], dtype=torch.complex64)
    target = torch.tensor([0, 0, 1, 1])
    assert torch.allclose(accumulate_power(contrib, target, 2), torch.tensor([0.0, 4.25]))
