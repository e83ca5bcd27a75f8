"""Geographic input: projection to the local ENU frame."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd

from rflscm.data import Origin, enu_to_geodetic, geodetic_to_enu, load_scenario, read_table, write_table

ORIGIN = Origin(lat=48.14, lon=11.57, height_m=500.0)
# WGS84 meridian / prime-vertical radii at the origin's latitude, for independent small-offset checks
_A, _E2 = 6378137.0, 6.69437999014e-3
_S2 = math.sin(math.radians(ORIGIN.lat)) ** 2
M_RADIUS = _A * (1 - _E2) / (1 - _E2 * _S2) ** 1.5
N_RADIUS = _A / math.sqrt(1 - _E2 * _S2)


def test_point_100m_north_and_east() -> None:
    dlat = math.degrees(100.0 / M_RADIUS)
    dlon = math.degrees(100.0 / (N_RADIUS * math.cos(math.radians(ORIGIN.lat))))
    xyz = geodetic_to_enu(
        np.array([ORIGIN.lat, ORIGIN.lat + dlat, ORIGIN.lat]),
        np.array([ORIGIN.lon, ORIGIN.lon, ORIGIN.lon + dlon]),
        np.array([500.0, 510.0, 530.0]),
        ORIGIN,
    )
    np.testing.assert_allclose(xyz[0], [0.0, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(xyz[1], [0.0, 100.0, 10.0], atol=1e-3)
    np.testing.assert_allclose(xyz[2], [100.0, 0.0, 30.0], atol=1e-2)


def test_inverse_round_trip() -> None:
    rng = np.random.default_rng(0)
    xyz = rng.uniform(-3000, 3000, size=(50, 3))
    lat, lon, h = enu_to_geodetic(xyz, ORIGIN)
    np.testing.assert_allclose(geodetic_to_enu(lat, lon, h, ORIGIN), xyz, atol=1e-6)


def test_scenario_with_lat_lon_tables(tiny_dir: Path, edit_yaml) -> None:
    reference = load_scenario(tiny_dir)
    for name in ("cells_round1.csv", "cells_round2.csv", "grids.csv"):
        df = read_table(tiny_dir / name)
        lat, lon, h = enu_to_geodetic(df[["x", "y", "z"]].to_numpy(), ORIGIN)
        df = df.drop(columns=["x", "y", "z"]).assign(lat=lat, lon=lon, height_m=h)
        write_table(df, tiny_dir / name)
    edit_yaml(tiny_dir, lambda d: d.update(origin={"lat": ORIGIN.lat, "lon": ORIGIN.lon, "height_m": 500.0}))
    sc = load_scenario(tiny_dir)
    assert "lat" not in sc.grids.columns and "lat" not in sc.cells[1].columns
    for table, ref in ((sc.grids, reference.grids), (sc.cells[1], reference.cells[1])):
        np.testing.assert_allclose(table[["x", "y", "z"]].to_numpy(), ref[["x", "y", "z"]].to_numpy(), atol=1e-6)
    pd.testing.assert_frame_equal(sc.measurements, reference.measurements)
