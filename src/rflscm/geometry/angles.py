"""Angle conventions — the one place that translates (SPEC §2).

Tables speak the planning tools' language: azimuth in degrees clockwise from
north, tilts in degrees positive *down*.  The code works in (elevation above
the horizon, azimuth counter-clockwise from east) in radians, in a local ENU
frame (x east, y north, z up).  Nothing else in the package converts.
"""

from __future__ import annotations

import numpy as np
import torch


def engineering_to_internal(
    azimuth_deg: np.ndarray | float, tilt_deg: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray]:
    """Planning-tool angles to code angles.

    Args:
        azimuth_deg: azimuth clockwise from north [deg].
        tilt_deg: tilt below the horizon, positive down [deg].

    Returns:
        ``(elevation_rad, azimuth_rad)``: elevation above the horizon and azimuth
        counter-clockwise from east, azimuth wrapped to [0, 2π) [rad].
    """
    az = np.deg2rad(90.0 - np.asarray(azimuth_deg, dtype=np.float64)) % (2 * np.pi)
    el = -np.deg2rad(np.asarray(tilt_deg, dtype=np.float64))
    return el, az


def internal_to_engineering(
    elevation_rad: np.ndarray | float, azimuth_rad: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`engineering_to_internal`: returns ``(azimuth_deg in [0, 360), tilt_deg)``."""
    azimuth_deg = (90.0 - np.rad2deg(np.asarray(azimuth_rad, dtype=np.float64))) % 360.0
    tilt_deg = -np.rad2deg(np.asarray(elevation_rad, dtype=np.float64))
    return azimuth_deg, tilt_deg


def unit_vectors(elevation_rad: torch.Tensor, azimuth_rad: torch.Tensor) -> torch.Tensor:
    """Direction unit vectors ``[..., 3]`` (ENU) from elevation/azimuth [rad] of shape ``[...]``."""
    cos_el = torch.cos(elevation_rad)
    return torch.stack(
        (cos_el * torch.cos(azimuth_rad), cos_el * torch.sin(azimuth_rad), torch.sin(elevation_rad)),
        dim=-1,
    )


def angles_of(directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(elevation_rad, azimuth_rad in [0, 2π))`` of direction vectors ``[..., 3]`` (need not be unit)."""
    x, y, z = directions.unbind(-1)
    elevation = torch.atan2(z, torch.sqrt(x * x + y * y))
    azimuth = torch.remainder(torch.atan2(y, x), 2 * torch.pi)
    return elevation, azimuth


def rotation_matrix(azimuth_rad: float, downtilt_rad: float) -> np.ndarray:
    """Antenna-to-world rotation ``[3, 3]``.

    The antenna frame has boresight along +x, the array's rows along +y and its
    columns along +z.  The antenna is first tilted down by ``downtilt_rad``
    (rotation about y taking +x towards −z), then turned to ``azimuth_rad``
    (CCW from east, about z).  World vectors map to antenna vectors by ``R.T``.
    """
    ca, sa = np.cos(azimuth_rad), np.sin(azimuth_rad)
    ct, st = np.cos(downtilt_rad), np.sin(downtilt_rad)
    rz = np.array([[ca, -sa, 0.0], [sa, ca, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[ct, 0.0, st], [0.0, 1.0, 0.0], [-st, 0.0, ct]])
    return rz @ ry
