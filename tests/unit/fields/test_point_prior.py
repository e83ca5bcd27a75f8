"""Point-cloud prior Φ (paper eqs. (14)–(17))."""

from __future__ import annotations

import numpy as np
import torch

from rflscm.fields import PointPrior, density_grid, fdam_attenuation, modulate, phi_of_density


def test_density_counts_points_within_radius() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform([0, 0, 0], [20, 20, 6], (500, 3))
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([20.0, 20.0, 6.0])
    density, glo, ghi = density_grid(pts, lo, hi, voxel_m=2.0, radius_m=3.0)
    assert density.shape == (11, 11, 4) and np.allclose(glo, lo) and np.allclose(ghi, [20, 20, 6])
    for idx in [(0, 0, 0), (5, 5, 1), (10, 3, 3), (7, 9, 2)]:
        centre = glo + 2.0 * np.array(idx)
        brute = int((np.linalg.norm(pts - centre, axis=1) <= 3.0).sum())
        assert density[idx] == brute


def test_density_equals_a_kd_tree_ball_count_everywhere() -> None:
    """The stencil count is the exact ball count at every grid point (also for points outside the box and radii
    that are not a multiple of the voxel), checked against scipy's KD-tree."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(1)
    pts = rng.uniform([-3, -3, -1], [23, 17, 7], (800, 3))
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([20.0, 15.0, 6.0])
    for voxel, radius in ((2.0, 3.0), (1.5, 4.2), (3.0, 2.0)):
        density, glo, _ = density_grid(pts, lo, hi, voxel_m=voxel, radius_m=radius)
        centres = glo + np.argwhere(np.ones(density.shape, bool)) * voxel
        balls = cKDTree(pts).query_ball_point(centres, r=radius)
        assert np.array_equal(density.ravel(), np.array([len(b) for b in balls], np.float32))


def test_density_folds_held_hits_without_changing_counts(monkeypatch) -> None:
    import rflscm.fields.point_prior as pp

    pts = np.random.default_rng(2).uniform(0, 12, (300, 3))
    whole, _, _ = density_grid(pts, np.zeros(3), np.full(3, 12.0), voxel_m=1.0, radius_m=2.0)
    monkeypatch.setattr(pp, "FOLD_AT", 50)
    folded, _, _ = density_grid(pts, np.zeros(3), np.full(3, 12.0), voxel_m=1.0, radius_m=2.0)
    assert whole.sum() > 50 * 10 and np.array_equal(whole, folded)


def test_density_is_zero_far_from_points() -> None:
    pts = np.array([[1.0, 1.0, 1.0]])
    density, _, _ = density_grid(pts, np.zeros(3), np.array([40.0, 40.0, 10.0]), voxel_m=2.0, radius_m=2.5)
    assert density.sum() == (np.linalg.norm(np.argwhere(density >= 0) * 2.0 - 1.0, axis=1) <= 2.5).sum()
    assert density[10:, 10:, :].sum() == 0


def test_lookup_interpolates_between_grid_points() -> None:
    density = torch.zeros(3, 3, 3)
    density[1, 1, 1] = 8.0
    prior = PointPrior(density, torch.zeros(3), torch.full((3,), 4.0), threshold=5.0, beta=0.1)
    pts = torch.tensor([[2.0, 2.0, 2.0], [3.0, 2.0, 2.0], [0.0, 0.0, 0.0], [50.0, 2.0, 2.0]])
    assert torch.allclose(prior.density(pts), torch.tensor([8.0, 4.0, 0.0, 0.0]))
    assert torch.allclose(prior(pts), torch.tensor([1.0, 0.4, 0.0, 0.0]))


def test_phi_threshold() -> None:
    d = torch.tensor([0.0, 2.0, 10.0, 10.5, 40.0])
    assert torch.allclose(phi_of_density(d, 10.0, 0.02), torch.tensor([0.0, 0.04, 0.2, 1.0, 1.0]))


def test_zero_phi_makes_a_sample_inert() -> None:
    eps = torch.tensor([[4.0 - 1.0j, 9.0 - 2.0j]], dtype=torch.complex128)
    log_delta = fdam_attenuation(torch.ones_like(eps), eps, 0.1, 4.0, log=True)
    radiance = torch.tensor([[2.0 + 1.0j, -3.0j]], dtype=torch.complex128)
    r_tilde, log_delta_tilde = modulate(torch.zeros(1, 2, dtype=torch.float64), radiance, log_delta)
    assert torch.equal(r_tilde, torch.zeros_like(radiance))
    assert torch.allclose(torch.exp(log_delta_tilde), torch.ones_like(radiance))
    # Φ = 1 keeps the learned values, Φ = ½ takes the square root of |δ|
    _, full = modulate(torch.ones(1, 2, dtype=torch.float64), radiance, log_delta)
    _, half = modulate(torch.full((1, 2), 0.5, dtype=torch.float64), radiance, log_delta)
    assert torch.allclose(torch.exp(full), torch.exp(log_delta))
    assert torch.allclose(torch.exp(half).abs(), torch.exp(log_delta).abs().sqrt())
