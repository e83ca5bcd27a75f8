"""FDAM (paper eq. (8)) and the passive medium parameterisation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from rflscm.fields import PassiveMedium, fdam_attenuation
from rflscm.fields.fdam import DB_PER_NEPER


def reference_fdam(mu: np.ndarray, eps: np.ndarray, wavelength: float, d: float) -> np.ndarray:
    """Eq. (8) written out voxel by voxel, free space before and after (independent of the torch code)."""
    z = [1.0 + 0j, *list(np.sqrt(mu / eps)), 1.0 + 0j]
    out = []
    for q in range(len(mu)):
        g = (z[q + 1] - z[q]) / (z[q + 1] + z[q])
        g_next = (z[q + 2] - z[q + 1]) / (z[q + 2] + z[q + 1])
        t = np.exp(-1j * 2 * np.pi / wavelength * np.sqrt(eps[q] * mu[q]) * d)
        out.append((1 - g) * t / (1 + g * g_next * t * t))
    return np.array(out)


def c128(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, dtype=np.complex128))


def test_free_space_is_pure_phase() -> None:
    wl, d = 0.0857, 4.0
    ones = torch.ones(1, 5, dtype=torch.complex128)
    delta = fdam_attenuation(ones, ones, wl, d)
    assert torch.allclose(delta.abs(), torch.ones(1, 5, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(delta, torch.full_like(delta, complex(np.exp(-1j * 2 * np.pi / wl * d))), atol=1e-9)


def test_matches_reference_formula() -> None:
    rng = np.random.default_rng(1)
    eps = 1 + rng.exponential(2, 7) - 1j * rng.exponential(0.05, 7)
    mu = 1 + rng.exponential(0.5, 7) + 0j
    ref = reference_fdam(mu, eps, 0.142, 3.0)
    got = fdam_attenuation(c128(mu), c128(eps), 0.142, 3.0).numpy()
    np.testing.assert_allclose(got, ref, rtol=1e-10)


def test_log_form_is_log_of_delta() -> None:
    rng = np.random.default_rng(2)
    eps = c128(1 + rng.exponential(3, (4, 9)) - 1j * rng.exponential(0.1, (4, 9)))
    mu = torch.ones_like(eps)
    delta = fdam_attenuation(mu, eps, 0.1, 4.0)
    assert torch.allclose(torch.exp(fdam_attenuation(mu, eps, 0.1, 4.0, log=True)), delta, atol=1e-10)


def test_first_last_masks_split_concatenated_rays() -> None:
    rng = np.random.default_rng(3)
    eps = 1 + rng.exponential(2, 6) - 1j * rng.exponential(0.05, 6)
    mu = np.ones(6, complex)
    first = torch.tensor([True, False, False, True, False, False])
    last = torch.tensor([False, False, True, False, False, True])
    got = fdam_attenuation(c128(mu), c128(eps), 0.1, 2.0, first=first, last=last).numpy()
    ref = np.concatenate([reference_fdam(mu[:3], eps[:3], 0.1, 2.0), reference_fdam(mu[3:], eps[3:], 0.1, 2.0)])
    np.testing.assert_allclose(got, ref, rtol=1e-10)


passive = dict(
    eps_re=st.floats(1.0, 20.0),
    eps_im=st.floats(0.0, 5.0),
    mu_re=st.floats(1.0, 5.0),
    wavelength=st.floats(0.03, 0.5),
    d=st.floats(0.1, 8.0),
)


@settings(max_examples=300, deadline=None)
@given(**passive)
def test_passive_homogeneous_medium_never_amplifies(eps_re, eps_im, mu_re, wavelength, d) -> None:
    """Inside a homogeneous passive medium Γ = 0 and |δ| = |T| ≤ 1."""
    eps = torch.full((1, 4), complex(eps_re, -eps_im), dtype=torch.complex128)
    mu = torch.full((1, 4), complex(mu_re, 0.0), dtype=torch.complex128)
    delta = fdam_attenuation(mu, eps, wavelength, d)[0, 1:-1]  # interior voxels
    assert bool((delta.abs() <= 1 + 1e-12).all())


@settings(max_examples=300, deadline=None)
@given(**passive)
def test_passive_slab_in_free_space_transmits_at_most_one(eps_re, eps_im, mu_re, wavelength, d) -> None:
    """A passive voxel between free space: δ_q δ_{q+1} is the Fabry–Pérot slab transmission, |·| ≤ 1."""
    eps = c128([complex(eps_re, -eps_im), 1.0])
    mu = c128([complex(mu_re, 0.0), 1.0])
    delta = fdam_attenuation(mu, eps, wavelength, d)
    z = math.sqrt(1.0) * np.sqrt(complex(mu_re, 0) / complex(eps_re, -eps_im))
    r = (z - 1) / (z + 1)
    t = np.exp(-1j * 2 * np.pi / wavelength * np.sqrt(complex(eps_re, -eps_im) * mu_re) * d)
    slab = (1 - r * r) * t / (1 - r * r * t * t) * np.exp(-1j * 2 * np.pi / wavelength * d)  # textbook etalon
    product = complex(delta[0] * delta[1])
    assert abs(product - slab) < 1e-9
    assert abs(product) <= 1 + 1e-9


def test_single_entry_factor_can_exceed_one() -> None:
    """Why the renderer has a passivity guard: entering ε = 4 from free space, 1 − Γ = 4/3."""
    eps, mu = c128([4.0, 4.0, 4.0]), c128([1.0, 1.0, 1.0])
    gamma = (0.5 - 1.0) / (0.5 + 1.0)
    delta = fdam_attenuation(mu, eps, 0.1, 4.0)
    assert abs(abs(delta[0]) - (1 - gamma)) < 1e-9 and abs(delta[0]) > 1.3


@pytest.mark.parametrize("learn_mu", [True, False])
def test_passive_medium_constraints_and_loss_scale(learn_mu: bool) -> None:
    medium = PassiveMedium(reference_wavelength_m=0.0857, voxel_m=4.0, learn_mu=learn_mu)
    raw = 3.0 * torch.randn(2000, medium.num_channels, dtype=torch.float64)
    mu, eps = medium(raw)
    assert bool((eps.real >= 1 - 1e-9).all()) and bool((eps.imag <= 0).all())
    assert bool((mu.real >= 1).all()) and bool((mu.imag == 0).all())
    n = torch.sqrt(eps * mu)
    k_d = 2 * math.pi / 0.0857 * 4.0
    loss_db = -n.imag * k_d * DB_PER_NEPER
    assert torch.allclose(loss_db, medium.loss_db(raw), rtol=1e-6)


def test_passive_medium_initialises_near_free_space_and_scales_with_carrier() -> None:
    medium = PassiveMedium(reference_wavelength_m=0.0857, voxel_m=4.0, init_loss_db=0.01)
    mu, eps = medium(torch.zeros(1, 6, 3, dtype=torch.float64))
    assert torch.allclose(eps, torch.ones_like(eps), atol=1e-3) and torch.allclose(mu, torch.ones_like(mu), atol=1e-3)
    # 20 dB per voxel at the reference carrier → 20·λ_ref/λ dB at another carrier (constant n'')
    raw = torch.zeros(1, 6, 3, dtype=torch.float64)
    raw[..., 0] = math.log(20.0 / 0.01)
    raw[..., 1:] = -30.0  # no index excess, μ = 1: no reflections
    mu, eps = medium(raw)
    for wl in (0.0857, 0.1428):
        delta = fdam_attenuation(mu, eps, wl, 4.0)[0, 2]
        assert abs(-20 * math.log10(abs(delta)) - 20.0 * 0.0857 / wl) < 1e-6


def test_gradients_are_finite() -> None:
    medium = PassiveMedium(reference_wavelength_m=0.1, voxel_m=4.0)
    raw = torch.randn(3, 8, 3, requires_grad=True)
    mu, eps = medium(raw)
    fdam_attenuation(mu, eps, 0.1, 4.0, log=True).real.sum().backward()
    assert torch.isfinite(raw.grad).all() and raw.grad.abs().sum() > 0
