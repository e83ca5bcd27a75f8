"""The angular grid on which every APS lives (SPEC §2)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
import torch

from rflscm.errors import ConfigError
from rflscm.geometry.angles import angles_of, unit_vectors


@dataclass(frozen=True)
class AngleGrid:
    """Elevation × azimuth bins covering the whole sphere.

    Bin centres: elevation ``el_min_deg + i * el_step_deg`` for ``i < num_el``,
    azimuth (CCW from east) ``j * az_step_deg`` for ``j < num_az``.  The flat bin
    index is ``n = i * num_az + j`` (elevation-major).  Defaults: 91 × 72 = 6552
    bins, elevation −90°…+90° in 2° steps, azimuth in 5° steps.
    """

    num_el: int = 91
    num_az: int = 72
    el_min_deg: float = -90.0
    el_step_deg: float = 2.0

    def __post_init__(self) -> None:
        if self.num_el < 1 or self.num_az < 1:
            raise ConfigError(f"AngleGrid needs at least one bin per axis (got {self.num_el} × {self.num_az}).")
        top = self.el_min_deg + (self.num_el - 1) * self.el_step_deg
        if self.el_min_deg < -90.0 - 1e-9 or top > 90.0 + 1e-9 or self.el_step_deg <= 0:
            raise ConfigError(
                f"AngleGrid elevations must lie in −90…+90° (got {self.el_min_deg}…{top}° in {self.el_step_deg}° steps)."
            )

    def to_dict(self) -> dict[str, int | float]:
        """``{"num_el", "num_az", "el_min_deg", "el_step_deg"}``: how checkpoints and ``scenario.yaml`` store a grid."""
        return {
            "num_el": self.num_el,
            "num_az": self.num_az,
            "el_min_deg": self.el_min_deg,
            "el_step_deg": self.el_step_deg,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any] | list[Any] | tuple[Any, ...]) -> AngleGrid:
        """Inverse of :meth:`to_dict`; also reads the bare ``[num_el, num_az, el_min_deg, el_step_deg]`` of
        checkpoints written before it."""
        if isinstance(data, (list, tuple)):
            num_el, num_az, el_min, el_step = data
            data = {"num_el": num_el, "num_az": num_az, "el_min_deg": el_min, "el_step_deg": el_step}
        if not isinstance(data, dict) or set(data) != {"num_el", "num_az", "el_min_deg", "el_step_deg"}:
            raise ConfigError(f"an angle grid needs num_el, num_az, el_min_deg and el_step_deg (got {data!r}).")
        return cls(int(data["num_el"]), int(data["num_az"]), float(data["el_min_deg"]), float(data["el_step_deg"]))

    @classmethod
    def full_sphere(cls, num_el: int, num_az: int) -> AngleGrid:
        """A grid of ``num_el`` elevations spanning −90…+90° exactly and ``num_az`` azimuths."""
        step = 180.0 / (num_el - 1) if num_el > 1 else 1.0
        return cls(num_el=num_el, num_az=num_az, el_min_deg=-90.0 if num_el > 1 else 0.0, el_step_deg=step)

    @property
    def az_step_deg(self) -> float:
        return 360.0 / self.num_az

    @property
    def num_bins(self) -> int:
        return self.num_el * self.num_az

    @property
    def shape(self) -> tuple[int, int]:
        return (self.num_el, self.num_az)

    @cached_property
    def elevations_rad(self) -> np.ndarray:
        """Bin-centre elevations ``[num_el]`` [rad]."""
        return np.deg2rad(self.el_min_deg + self.el_step_deg * np.arange(self.num_el))

    @cached_property
    def azimuths_rad(self) -> np.ndarray:
        """Bin-centre azimuths ``[num_az]`` (CCW from east) [rad]."""
        return np.deg2rad(self.az_step_deg * np.arange(self.num_az))

    def bin_angles(self) -> tuple[np.ndarray, np.ndarray]:
        """``(elevation_rad [num_bins], azimuth_rad [num_bins])`` of every bin, flat order."""
        el, az = np.meshgrid(self.elevations_rad, self.azimuths_rad, indexing="ij")
        return el.ravel(), az.ravel()

    @cached_property
    def _directions_f64(self) -> torch.Tensor:
        el, az = self.bin_angles()
        return unit_vectors(torch.as_tensor(el, dtype=torch.float64), torch.as_tensor(az, dtype=torch.float64))

    def directions(self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None) -> torch.Tensor:
        """Unit vectors ``[num_bins, 3]`` (ENU) of the bin centres (computed once, in float64)."""
        return self._directions_f64.to(dtype=dtype, device=device)

    def bin_of(self, elevation_rad: np.ndarray, azimuth_rad: np.ndarray) -> np.ndarray:
        """Flat bin index (int64) of the nearest bin centre of each direction [rad]."""
        el_deg = np.rad2deg(np.asarray(elevation_rad, dtype=np.float64))
        az_deg = np.rad2deg(np.asarray(azimuth_rad, dtype=np.float64))
        i = np.clip(np.rint((el_deg - self.el_min_deg) / self.el_step_deg), 0, self.num_el - 1).astype(np.int64)
        j = np.rint(np.mod(az_deg, 360.0) / self.az_step_deg).astype(np.int64) % self.num_az
        return i * self.num_az + j

    def bin_of_vectors(self, directions: torch.Tensor) -> torch.Tensor:
        """Flat bin index ``[...]`` of direction vectors ``[..., 3]``."""
        el, az = angles_of(directions.double())
        return torch.as_tensor(self.bin_of(el.cpu().numpy(), az.cpu().numpy()), device=directions.device)

    # --- HiTAM coarse/fine block mapping --------------------------------------------------------
    def coarse(self, beta: int) -> CoarseMapping:
        """The β × β coarse grid over this grid (partial edge blocks allowed)."""
        return CoarseMapping(self, beta)


class CoarseMapping:
    """Maps a fine :class:`AngleGrid` to coarse blocks of β × β fine bins.

    Coarse bin ``(I, J)`` covers fine elevations ``I*β … min((I+1)*β, num_el) − 1``
    and fine azimuths ``J*β … min((J+1)*β, num_az) − 1``: edge blocks are partial.
    The coarse bin's representative direction is its first fine bin (every β-th
    bin on both axes), as in the paper's coarse set Ω.
    """

    def __init__(self, fine: AngleGrid, beta: int) -> None:
        if beta < 1:
            raise ConfigError(f"HiTAM beta must be >= 1 (got {beta}).")
        self.fine = fine
        self.beta = beta
        self.num_el = -(-fine.num_el // beta)
        self.num_az = -(-fine.num_az // beta)
        # Fine index of every (coarse, sub-bin) pair, -1 where the block is partial.
        ci, cj, si, sj = np.meshgrid(
            np.arange(self.num_el), np.arange(self.num_az), np.arange(beta), np.arange(beta), indexing="ij"
        )
        fi, fj = ci * beta + si, cj * beta + sj
        valid = (fi < fine.num_el) & (fj < fine.num_az)
        table = np.where(valid, fi * fine.num_az + fj, -1).reshape(self.num_bins, beta * beta)
        self._children = torch.as_tensor(table, dtype=torch.long)
        rep_i, rep_j = np.meshgrid(np.arange(self.num_el) * beta, np.arange(self.num_az) * beta, indexing="ij")
        self._representative = torch.as_tensor((rep_i * fine.num_az + rep_j).ravel(), dtype=torch.long)

    @property
    def num_bins(self) -> int:
        return self.num_el * self.num_az

    def representative_bins(self) -> torch.Tensor:
        """Fine bin index ``[num_coarse]`` of each coarse bin's direction."""
        return self._representative

    def children(self, coarse_bins: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Fine bins of coarse bins ``[...]``.

        Returns ``(fine_bins [..., β²], valid [..., β²])``; invalid slots (outside a
        partial edge block) hold fine bin 0 and ``valid = False``.
        """
        table = self._children.to(coarse_bins.device)[coarse_bins]
        valid = table >= 0
        return table.clamp_min(0), valid

    def parent_of(self) -> torch.Tensor:
        """Coarse bin ``[num_fine]`` containing each fine bin."""
        i = torch.arange(self.fine.num_el) // self.beta
        j = torch.arange(self.fine.num_az) // self.beta
        return (i[:, None] * self.num_az + j[None, :]).reshape(-1)
