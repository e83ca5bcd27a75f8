"""Frequency-dependent attenuation model (FDAM, paper §III-B, eqs. (5)–(8)) and a passive,
well-scaled parameterisation of the media it acts on (SPEC §3, numerical notes).

FDAM, for voxel q of a ray (free space before the first and after the last voxel):

    Z_q = √(μ_q / ε_q)                                  normalised impedance
    Γ_q = (Z_q − Z_{q−1}) / (Z_q + Z_{q−1})             Fresnel reflection, eq. (5)
    T_q = exp(−j 2π/λ · √(ε_q μ_q) · d)                 propagation through the voxel, eq. (6)
    δ_q = (1 − Γ_q) T_q / (1 + Γ_q Γ_{q+1} T_q²)         transmission + Fabry–Pérot cascade, eq. (8)

Note on passivity: |T_q| ≤ 1 and Γ = 0 in a homogeneous medium, and a single slab in free
space transmits |δ_q δ_{q+1}| ≤ 1.  A *single* δ_q can exceed 1, however (entering a denser
medium, 1 − Γ_q > 1; the exit factor pays it back), and FDAM's per-voxel cascade is not exactly
energy-conserving through several different layers.  The renderer therefore offers a passivity
guard on the cumulative transmittance (:func:`rflscm.render.aps.transmittance`); δ stays exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

DB_PER_NEPER = 20.0 / math.log(10.0)  # amplitude: 1 Np = 8.686 dB


def fdam_attenuation(
    mu: torch.Tensor,
    eps: torch.Tensor,
    wavelength_m: torch.Tensor | float,
    d_m: float,
    log: bool = False,
    first: torch.Tensor | None = None,
    last: torch.Tensor | None = None,
) -> torch.Tensor:
    """Expected attenuation δ (or log δ) of every voxel along rays, paper eq. (8).

    Args:
        mu, eps: complex relative permeability / permittivity ``[..., num_samples]``, consecutive
            voxels of a ray along the last axis; free space (μ = ε = 1) lies before the first and
            after the last voxel.
        wavelength_m: carrier wavelength [m], broadcastable to ``mu``.
        d_m: voxel thickness d [m].
        log: return log δ on the continuous branch, log(1 − Γ_q) − j k √(εμ) d − log(1 + Γ_qΓ_{q+1}T_q²),
            whose exponential is δ exactly; its imaginary part is the unwrapped phase, so that the
            point-cloud power δ^Φ = exp(Φ log δ) is continuous in the parameters.
        first, last: bool masks like ``mu`` for a last axis that concatenates several rays: where
            ``first`` (``last``) is set, the previous (next) voxel is free space.

    Returns:
        complex ``[..., num_samples]``.
    """
    z = torch.sqrt(mu / eps)  # Z_q
    free = torch.ones_like(z[..., :1])
    z_prev = torch.cat((free, z[..., :-1]), dim=-1)
    z_next = torch.cat((z[..., 1:], free), dim=-1)
    if first is not None:
        z_prev = torch.where(first, torch.ones_like(z), z_prev)
    if last is not None:
        z_next = torch.where(last, torch.ones_like(z), z_next)
    gamma = (z - z_prev) / (z + z_prev)  # Γ_q, interface q−1 → q   (eq. (5))
    gamma_next = (z_next - z) / (z_next + z)  # Γ_{q+1}, interface q → q+1
    if isinstance(wavelength_m, torch.Tensor):
        wavelength_m = wavelength_m.to(z.real.dtype)
    log_t = -1j * (2.0 * math.pi / wavelength_m) * torch.sqrt(eps * mu) * d_m  # log T_q   (eq. (6))
    t = torch.exp(log_t)
    denominator = 1.0 + gamma * gamma_next * t * t
    if log:
        return torch.log(1.0 - gamma) + log_t - torch.log(denominator)
    return (1.0 - gamma) * t / denominator  # δ_q   (eq. (8))


@dataclass(frozen=True)
class PassiveMedium:
    """Maps unconstrained field channels to passive (μ, ε), free space at raw = −∞ and ≈ free space at 0.

    Channels of the δ field (raw values r₀, r₁[, r₂]):

    * r₀ — per-voxel one-way loss at the reference carrier on a log scale:
      loss_dB = ``init_loss_db`` · exp(r₀); it is converted to the medium property
      n'' = −Im √(εμ) = loss_dB / (8.686 · k_ref · d), so that at carrier λ the voxel loses
      loss_dB · λ_ref/λ (FDAM's frequency dependence stays physical) while one optimizer step
      changes the loss by a factor, whatever its size (the stiffness note of SPEC §3);
    * r₁ — excess real index n' − √(μ' + n''²) = ``init_index_excess`` · exp(r₁) ≥ 0;
    * r₂ — with ``learn_mu``: μ' − 1 = ``init_mu_excess`` · exp(r₂) ≥ 0 (μ real: magnetic loss is
      folded into n''), else μ = 1.

    Then n = n' − j n'', μ = μ', ε = n²/μ, which satisfies Re ε ≥ 1, Im ε ≤ 0, Re μ ≥ 1,
    Im μ = 0 and √(εμ) = n exactly.  (The paper's D_δ = 4 channels are Re/Im of μ and ε;
    the passive constraints leave 3 free quantities, 2 with μ fixed.)
    """

    reference_wavelength_m: float
    voxel_m: float
    learn_mu: bool = True
    init_loss_db: float = 0.01
    init_index_excess: float = 1e-4
    init_mu_excess: float = 1e-4
    max_loss_db: float = 60.0
    max_index: float = 10.0

    @property
    def num_channels(self) -> int:
        return 3 if self.learn_mu else 2

    def loss_db(self, raw: torch.Tensor) -> torch.Tensor:
        """Per-voxel loss [dB] at the reference carrier ``[...]`` from raw channels ``[..., C]``."""
        cap = math.log(self.max_loss_db / self.init_loss_db)
        return self.init_loss_db * torch.exp(raw[..., 0].clamp(max=cap))

    def __call__(self, raw: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Raw channels ``[..., C]`` → complex ``(mu, eps)`` ``[...]``."""
        k_ref_d = 2.0 * math.pi / self.reference_wavelength_m * self.voxel_m
        n_imag = self.loss_db(raw) / (DB_PER_NEPER * k_ref_d)  # n''
        if self.learn_mu:
            cap = math.log(self.max_index / self.init_mu_excess)
            mu_real = 1.0 + self.init_mu_excess * torch.exp(raw[..., 2].clamp(max=cap))
        else:
            mu_real = torch.ones_like(n_imag)
        cap = math.log(self.max_index / self.init_index_excess)
        excess = self.init_index_excess * torch.exp(raw[..., 1].clamp(max=cap))
        n_real = torch.sqrt(mu_real + n_imag.square()) + excess
        n = torch.complex(n_real, -n_imag)
        mu = torch.complex(mu_real, torch.zeros_like(mu_real))
        return mu, n * n / mu
