"""Geographic input → the scenario's local metric ENU frame (SPEC §2).

The frame is a transverse-Mercator projection (WGS84 ellipsoid, scale 1)
centred on the scenario's origin: x east, y north, z up [m], with
z = height_m − origin.height_m.  Transverse Mercator is conformal, so antenna
azimuths measured from true north keep their meaning near the origin, and
distances along the central meridian are exact.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyproj

from rflscm.errors import ConfigError


@dataclass(frozen=True)
class Origin:
    """Geodetic origin of the local ENU frame."""

    lat: float
    """Latitude [deg], −90…90."""
    lon: float
    """Longitude [deg], −180…180."""
    height_m: float = 0.0
    """Ellipsoidal (or the tables' height reference) height of z = 0 [m]."""

    def __post_init__(self) -> None:
        if not -90.0 <= self.lat <= 90.0:
            raise ConfigError(f"`origin.lat` = {self.lat} must lie in −90…90°.")
        if not -180.0 <= self.lon <= 180.0:
            raise ConfigError(f"`origin.lon` = {self.lon} must lie in −180…180°.")


def _projection(origin: Origin) -> pyproj.Proj:
    return pyproj.Proj(proj="tmerc", lat_0=origin.lat, lon_0=origin.lon, k=1.0, x_0=0.0, y_0=0.0, ellps="WGS84")


def geodetic_to_enu(lat_deg: np.ndarray, lon_deg: np.ndarray, height_m: np.ndarray, origin: Origin) -> np.ndarray:
    """Local ENU coordinates ``[num_points, 3]`` [m] of geodetic points (each input ``[num_points]``, deg / m)."""
    x, y = _projection(origin)(np.asarray(lon_deg, np.float64), np.asarray(lat_deg, np.float64))
    z = np.asarray(height_m, np.float64) - origin.height_m
    return np.stack((np.asarray(x, np.float64), np.asarray(y, np.float64), z), axis=-1)


def enu_to_geodetic(xyz: np.ndarray, origin: Origin) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`geodetic_to_enu`: ``(lat_deg, lon_deg, height_m)``, each ``[num_points]``."""
    xyz = np.asarray(xyz, np.float64)
    lon, lat = _projection(origin)(xyz[:, 0], xyz[:, 1], inverse=True)
    return np.asarray(lat, np.float64), np.asarray(lon, np.float64), xyz[:, 2] + origin.height_m
