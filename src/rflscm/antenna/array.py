"""Uniform rectangular arrays and the cell antenna (position-free part of a cell)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from rflscm.antenna.element import ElementPattern, TR38901Element
from rflscm.errors import ConfigError
from rflscm.geometry.angles import engineering_to_internal, rotation_matrix

SPEED_OF_LIGHT = 299_792_458.0


def wavelength_of(freq_hz: float) -> float:
    """Carrier wavelength [m] of ``freq_hz`` [Hz]."""
    return SPEED_OF_LIGHT / float(freq_hz)


@dataclass(frozen=True)
class ArrayGeometry:
    """A uniform rectangular array in the antenna's y–z plane.

    ``num_h`` elements along the horizontal axis (+y, to the boresight's left)
    and ``num_v`` along the vertical axis (+z), centred on the phase centre.
    Spacing is physical [m]: at another carrier, d/λ changes.
    """

    num_h: int = 8
    num_v: int = 4
    spacing_h_m: float = 0.5 * SPEED_OF_LIGHT / 3.5e9
    spacing_v_m: float = 0.7 * SPEED_OF_LIGHT / 3.5e9

    def __post_init__(self) -> None:
        if self.num_h < 1 or self.num_v < 1:
            raise ConfigError(f"an array needs at least 1 × 1 elements (got {self.num_h} × {self.num_v}).")
        if self.spacing_h_m <= 0 or self.spacing_v_m <= 0:
            raise ConfigError(f"element spacings must be > 0 m (got {self.spacing_h_m}, {self.spacing_v_m}).")

    @classmethod
    def for_frequency(
        cls, design_freq_hz: float, num_h: int = 8, num_v: int = 4, spacing_h_wl: float = 0.5, spacing_v_wl: float = 0.7
    ) -> ArrayGeometry:
        """Array whose spacings are ``spacing_*_wl`` wavelengths at ``design_freq_hz`` (SPEC §2 defaults)."""
        wl = wavelength_of(design_freq_hz)
        return cls(num_h=num_h, num_v=num_v, spacing_h_m=spacing_h_wl * wl, spacing_v_m=spacing_v_wl * wl)

    @property
    def num_elements(self) -> int:
        return self.num_h * self.num_v

    def element_positions(self) -> np.ndarray:
        """Element positions ``[num_h, num_v, 3]`` in the antenna frame [m]."""
        y = (np.arange(self.num_h) - (self.num_h - 1) / 2) * self.spacing_h_m
        z = (np.arange(self.num_v) - (self.num_v - 1) / 2) * self.spacing_v_m
        yy, zz = np.meshgrid(y, z, indexing="ij")
        return np.stack((np.zeros_like(yy), yy, zz), axis=-1)


@dataclass(frozen=True)
class CellAntenna:
    """Orientation, array, element and power of one cell's antenna.

    Angles use the planning-tool convention of the cell tables (SPEC §2):
    ``azimuth_deg`` clockwise from north, tilts positive down.
    """

    azimuth_deg: float = 0.0
    mech_tilt_deg: float = 0.0
    elec_tilt_deg: float = 0.0
    array: ArrayGeometry = field(default_factory=ArrayGeometry)
    element: ElementPattern = field(default_factory=TR38901Element)
    tx_power_dbm: float = 15.0
    """Reference-signal power per resource element (EPRE) [dBm]."""

    def __post_init__(self) -> None:
        for name in ("mech_tilt_deg", "elec_tilt_deg"):
            value = getattr(self, name)
            if not -90.0 <= value <= 90.0:
                raise ConfigError(f"`{name}` must lie in −90…90° (positive = down); got {value}.")

    @property
    def tx_power_mw(self) -> float:
        return 10.0 ** (self.tx_power_dbm / 10.0)

    def rotation(self) -> np.ndarray:
        """Antenna-to-world rotation ``[3, 3]`` (mechanical azimuth and down-tilt)."""
        el, az = engineering_to_internal(self.azimuth_deg, self.mech_tilt_deg)
        return rotation_matrix(float(az), -float(el))

    def rotated(self, d_azimuth_deg: float = 0.0, d_mech_tilt_deg: float = 0.0) -> CellAntenna:
        """The same antenna turned by ``d_azimuth_deg`` (clockwise) and tilted by ``d_mech_tilt_deg`` (down)."""
        from dataclasses import replace

        return replace(
            self,
            azimuth_deg=(self.azimuth_deg + d_azimuth_deg) % 360.0,
            mech_tilt_deg=self.mech_tilt_deg + d_mech_tilt_deg,
        )


def steering_vectors(array: ArrayGeometry, local_directions: torch.Tensor, wavelength_m: float) -> torch.Tensor:
    """Array response ``[num_dirs, num_h * num_v]`` (complex) for antenna-frame unit vectors ``[num_dirs, 3]``.

    a_e(ω) = exp(j 2π/λ ⟨r_e, ω⟩), r_e the element positions (flattened h-major).
    """
    pos = torch.as_tensor(
        array.element_positions().reshape(-1, 3), dtype=local_directions.dtype, device=local_directions.device
    )
    phase = (2 * torch.pi / wavelength_m) * (local_directions @ pos.T)
    return torch.polar(torch.ones_like(phase), phase)
