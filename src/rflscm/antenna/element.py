"""Antenna element patterns: 3GPP TR 38.901 and measured (Planet/MSI) patterns.

An element pattern maps directions in the *antenna* frame (boresight +x, z up)
to a power gain in linear units.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from rflscm.errors import ConfigError


def _local_angles_deg(directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Zenith θ ∈ [0, 180] and azimuth φ ∈ (−180, 180] [deg] of antenna-frame directions ``[..., 3]``."""
    x, y, z = directions.unbind(-1)
    theta = torch.rad2deg(torch.atan2(torch.sqrt(x * x + y * y), z))
    phi = torch.rad2deg(torch.atan2(y, x))
    return theta, phi


@dataclass(frozen=True)
class TR38901Element:
    """The 3GPP TR 38.901 Table 7.3-1 sector element pattern."""

    hpbw_h_deg: float = 65.0
    hpbw_v_deg: float = 65.0
    max_attenuation_db: float = 30.0
    """Front-back ratio A_m and side-lobe limit SLA_V [dB]."""
    max_gain_dbi: float = 8.0

    def __post_init__(self) -> None:
        if self.hpbw_h_deg <= 0 or self.hpbw_v_deg <= 0:
            raise ConfigError(f"element half-power beam widths must be > 0 (got {self.hpbw_h_deg}, {self.hpbw_v_deg}).")

    def gain_db(self, directions: torch.Tensor) -> torch.Tensor:
        """Gain [dBi] ``[...]`` for antenna-frame unit vectors ``[..., 3]``."""
        theta, phi = _local_angles_deg(directions)
        a_v = -torch.clamp(12.0 * ((theta - 90.0) / self.hpbw_v_deg) ** 2, max=self.max_attenuation_db)
        a_h = -torch.clamp(12.0 * (phi / self.hpbw_h_deg) ** 2, max=self.max_attenuation_db)
        return self.max_gain_dbi - torch.clamp(-(a_v + a_h), max=self.max_attenuation_db)

    def gain_lin(self, directions: torch.Tensor) -> torch.Tensor:
        """Gain [linear] ``[...]`` for antenna-frame unit vectors ``[..., 3]``."""
        return torch.pow(10.0, self.gain_db(directions) / 10.0)

    @property
    def peak_gain_lin(self) -> float:
        return 10.0 ** (self.max_gain_dbi / 10.0)


@dataclass(frozen=True)
class MeasuredElement:
    """A measured element pattern (e.g. from a Planet/MSI file).

    ``horizontal_loss_db[k]`` is the loss at azimuth k·360/n_h degrees
    (counter-clockwise from boresight, as MSI files list it) and
    ``vertical_loss_db[k]`` the loss at k·360/n_v degrees of *depression* below
    boresight (MSI: 0 = boresight, 90 = straight down, 270 = straight up).  The 3-D
    gain is the usual sum of the two cuts, capped at ``max_attenuation_db``.
    """

    max_gain_dbi: float
    horizontal_loss_db: tuple[float, ...]
    vertical_loss_db: tuple[float, ...]
    max_attenuation_db: float = 40.0
    name: str = "measured"
    frequency_hz: float | None = None
    """Carrier the pattern was measured at (MSI ``FREQUENCY``) [Hz]; ``None`` = not stated (any band)."""

    def _interp(self, table: tuple[float, ...], angle_deg: torch.Tensor) -> torch.Tensor:
        values = torch.as_tensor(table, dtype=angle_deg.dtype, device=angle_deg.device)
        n = values.numel()
        pos = torch.remainder(angle_deg, 360.0) * (n / 360.0)
        lo = torch.floor(pos).long() % n
        hi = (lo + 1) % n
        frac = pos - torch.floor(pos)
        return values[lo] * (1 - frac) + values[hi] * frac

    def gain_db(self, directions: torch.Tensor) -> torch.Tensor:
        theta, phi = _local_angles_deg(directions)
        # MSI horizontal angles run counter-clockwise seen from above; vertical ones are depression angles.
        loss_h = self._interp(self.horizontal_loss_db, phi)
        loss_v = self._interp(self.vertical_loss_db, theta - 90.0)
        return self.max_gain_dbi - torch.clamp(loss_h + loss_v, max=self.max_attenuation_db)

    def gain_lin(self, directions: torch.Tensor) -> torch.Tensor:
        return torch.pow(10.0, self.gain_db(directions) / 10.0)

    @property
    def peak_gain_lin(self) -> float:
        return 10.0 ** (self.max_gain_dbi / 10.0)


ElementPattern = TR38901Element | MeasuredElement
