"""Terrain: heights above ground on a sloped DEM (XYZ table and GeoTIFF), coverage and plausibility."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pyproj
import pytest

from rflscm.data import load_scenario
from rflscm.data.geo import Origin, enu_to_geodetic
from rflscm.errors import DataError

ORIGIN = Origin(lat=48.1, lon=11.6, height_m=0.0)


def _plane_xyz(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 520.0 + 0.05 * x - 0.02 * y  # a slope: bilinear interpolation of a plane is exact


def _to_geographic(tiny_dir: Path, edit_table: Callable, edit_yaml: Callable, terrain: str | None) -> None:
    """Tiny scenario with lat/lon/height_m tables (height_m = the tiny's z, now above ground) and an origin."""

    def geo(df: pd.DataFrame) -> pd.DataFrame:
        lat, lon, _ = enu_to_geodetic(df[["x", "y", "z"]].to_numpy(np.float64), ORIGIN)
        return df.assign(lat=lat, lon=lon, height_m=df["z"]).drop(columns=["x", "y", "z"])

    for name in ("cells_round1.csv", "cells_round2.csv", "grids.csv"):
        edit_table(tiny_dir / name, geo)

    def yaml_change(d: dict) -> None:
        d["origin"] = {"lat": ORIGIN.lat, "lon": ORIGIN.lon, "height_m": ORIGIN.height_m}
        d.pop("point_cloud", None)  # the tiny cloud sits at absolute z near 0
        if terrain:
            d["terrain"] = terrain

    edit_yaml(tiny_dir, yaml_change)


def test_xyz_terrain_puts_heights_above_ground(tiny_dir: Path, edit_table: Callable, edit_yaml: Callable) -> None:
    x, y = np.meshgrid(np.arange(-300.0, 301.0, 50.0), np.arange(-250.0, 251.0, 25.0), indexing="ij")
    pd.DataFrame({"x": x.ravel(), "y": y.ravel(), "z": _plane_xyz(x, y).ravel()}).to_csv(
        tiny_dir / "dem.xyz", sep=" ", index=False
    )
    _to_geographic(tiny_dir, edit_table, edit_yaml, "dem.xyz")
    sc = load_scenario(tiny_dir)
    cell = sc.cell_position(11)
    assert cell[2] == pytest.approx(_plane_xyz(cell[0], cell[1]) + 25.0, abs=1e-6)
    grids = sc.grids[["x", "y", "z"]].to_numpy()
    np.testing.assert_allclose(grids[:, 2], _plane_xyz(grids[:, 0], grids[:, 1]) + 1.5, atol=1e-6)
    assert sc.meta.terrain == "dem.xyz"


def test_geotiff_terrain_in_utm_is_transformed_to_the_scenario_frame(
    tiny_dir: Path, edit_table: Callable, edit_yaml: Callable
) -> None:
    import rasterio
    from affine import Affine

    utm = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:32632", always_xy=True)
    e0, n0 = utm.transform(ORIGIN.lon, ORIGIN.lat)
    step, size = 20.0, 40  # 800 m × 800 m around the origin
    west, north = e0 - 400.0, n0 + 400.0
    cols, rows = np.meshgrid(np.arange(size), np.arange(size))
    east, northing = west + step * (cols + 0.5), north - step * (rows + 0.5)
    dem = (300.0 + 0.04 * (east - e0) + 0.01 * (northing - n0)).astype(np.float64)
    profile = {"driver": "GTiff", "height": size, "width": size, "count": 1, "dtype": "float64"}
    transform = Affine.translation(west, north) @ Affine.scale(step, -step)
    with rasterio.open(tiny_dir / "dem.tif", "w", crs="EPSG:32632", transform=transform, **profile) as dst:
        dst.write(dem, 1)
    _to_geographic(tiny_dir, edit_table, edit_yaml, "dem.tif")
    sc = load_scenario(tiny_dir)
    grids = sc.grids[["x", "y", "z"]].to_numpy()
    lat, lon, _ = enu_to_geodetic(np.c_[grids[:, :2], np.zeros(len(grids))], ORIGIN)
    e, n = utm.transform(lon, lat)
    np.testing.assert_allclose(grids[:, 2], 300.0 + 0.04 * (e - e0) + 0.01 * (n - n0) + 1.5, atol=1e-6)


def test_point_outside_the_terrain_is_refused_in_one_line(
    tiny_dir: Path, edit_table: Callable, edit_yaml: Callable
) -> None:
    x, y = np.meshgrid(np.arange(-100.0, 101.0, 50.0), np.arange(-100.0, 101.0, 50.0), indexing="ij")
    pd.DataFrame({"x": x.ravel(), "y": y.ravel(), "z": _plane_xyz(x, y).ravel()}).to_csv(tiny_dir / "dem.csv")
    edit_table(tiny_dir / "grids.csv", lambda df: df.assign(x=[50.0, -40.0, 10.0], y=[80.0, -90.0, -150.0]))
    _to_geographic(tiny_dir, edit_table, edit_yaml, "dem.csv")
    with pytest.raises(DataError) as exc:
        load_scenario(tiny_dir)
    text = str(exc.value)
    assert "\n" not in text and "grids.csv row 3" in text and "outside the terrain 'dem.csv'" in text


@pytest.mark.parametrize(
    ("z_scale", "message"),
    [(1000.0, "outside the plausible"), (None, "regular grid")],
)
def test_implausible_or_irregular_terrain_is_refused(
    tiny_dir: Path, edit_table: Callable, edit_yaml: Callable, z_scale, message: str
) -> None:
    x, y = np.meshgrid(np.arange(-200.0, 201.0, 50.0), np.arange(-200.0, 201.0, 50.0), indexing="ij")
    df = pd.DataFrame({"x": x.ravel(), "y": y.ravel(), "z": _plane_xyz(x, y).ravel() * (z_scale or 1.0)})
    (df if z_scale else df.iloc[:-1]).to_csv(tiny_dir / "dem.csv", index=False)
    _to_geographic(tiny_dir, edit_table, edit_yaml, "dem.csv")
    with pytest.raises(DataError, match=message):
        load_scenario(tiny_dir)


def test_without_terrain_heights_stay_absolute(tiny_dir: Path, edit_table: Callable, edit_yaml: Callable) -> None:
    _to_geographic(tiny_dir, edit_table, edit_yaml, None)
    sc = load_scenario(tiny_dir)
    assert sc.cell_position(11)[2] == pytest.approx(25.0) and sc.meta.ground is None
