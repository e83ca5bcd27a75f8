"""The maps' CRS and raster lattice: the local projection is data.geo's (x/y ↔ lat/lon round-trips), a
scenario without an origin says its position is nominal, grids land one per pixel at the detected spacing,
and the shipped scenario's new origin leaves its fingerprint (and so its checkpoints) as they were."""

from __future__ import annotations

import dataclasses

import numpy as np
import pandas as pd
import pyproj
import pytest

from rflscm.data.geo import Origin, geodetic_to_enu
from rflscm.errors import DataError
from rflscm.maps import NOMINAL_ORIGIN, Lattice, MapFrame

MUNICH = Origin(lat=48.14, lon=11.57)


def test_the_proj_string_is_the_import_projection_and_round_trips() -> None:
    frame = MapFrame.of(MUNICH)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-2000.0, 2000.0, (50, 2))
    lon, lat = frame.lonlat(xy)
    back = geodetic_to_enu(lat, lon, np.zeros(len(xy)), MUNICH)[:, :2]  # the import path of data/geo.py
    np.testing.assert_allclose(back, xy, atol=1e-6)
    to_local = pyproj.Transformer.from_crs("EPSG:4326", pyproj.CRS.from_proj4(frame.proj4), always_xy=True)
    x, y = to_local.transform(lon, lat)
    np.testing.assert_allclose(np.column_stack([x, y]), xy, atol=1e-6)  # what a GIS reading the files computes
    assert abs(lat.mean() - 48.14) < 0.05 and abs(lon.mean() - 11.57) < 0.05
    assert "48.14" in frame.note and "NOMINAL" not in frame.note


def test_a_scenario_without_origin_gets_a_nominal_frame_that_says_so() -> None:
    frame = MapFrame.of(None)
    assert frame.nominal and frame.origin == NOMINAL_ORIGIN
    assert "NOMINAL" in frame.note and "+proj=tmerc" in frame.note
    lon, lat = frame.lonlat(np.array([[1000.0, 0.0]]))
    assert abs(lat[0]) < 1e-9 and 0.008 < lon[0] < 0.01  # 1 km east of 0°N 0°E


def test_lattice_detects_the_grid_spacing_and_puts_one_grid_per_pixel() -> None:
    xs, ys = np.meshgrid(np.arange(-75.0, 30.0, 10.0), np.arange(-315.0, -250.0, 10.0))
    xy = np.column_stack([xs.ravel(), ys.ravel()])[::3]  # a sparse subset of a 10 m lattice
    lat = Lattice.of(xy)
    assert lat.size_m == 10.0 and lat.width == 11 and lat.height == 7
    image = lat.image(np.arange(len(xy), dtype=np.float32), np.nan)
    assert np.isfinite(image).sum() == len(xy)  # every grid kept, nodata elsewhere
    assert image[lat.row, lat.col].tolist() == list(range(len(xy)))
    # pixel centre of grid 0 at its x/y
    assert lat.x_min + lat.col[0] * lat.size_m == xy[0, 0] and lat.y_max - lat.row[0] * lat.size_m == xy[0, 1]


def test_irregular_grids_never_share_a_pixel_and_absurd_spacing_is_refused() -> None:
    xy = np.array([[50.0, 80.0], [-40.0, -90.0], [10.0, -95.0], [12.5, 0.0]])
    lat = Lattice.of(xy)
    assert len({(r, c) for r, c in zip(lat.row, lat.col)}) == len(xy)
    with pytest.raises(DataError, match="regular spacing"):
        Lattice.of(np.array([[0.0, 0.0], [0.001, 5000.0], [5000.0, 0.0]]))


def test_shipped_scenario_has_a_munich_origin_and_the_same_fingerprint() -> None:
    from rflscm.data import load_scenario
    from rflscm.sim import default_scenario_path

    scenario = load_scenario(default_scenario_path())
    assert scenario.meta.origin is not None
    assert 48.0 < scenario.meta.origin.lat < 48.3 and 11.4 < scenario.meta.origin.lon < 11.8
    without = dataclasses.replace(scenario, meta=dataclasses.replace(scenario.meta, origin=None))
    assert without.fingerprint() == scenario.fingerprint()  # checkpoints trained before the origin stay valid
    assert scenario.fingerprint() == "a907802e0e19c9e430d47f96aa664916089a0af21b4c4d696362af2dc0b2fd81"


def test_with_grid_positions_puts_x_y_lat_lon_beside_grid_ids(tmp_path) -> None:
    from rflscm.data import load_scenario
    from rflscm.data.examples import tiny_scenario
    from rflscm.maps.vector import with_grid_positions

    root = tiny_scenario(tmp_path / "t")
    text = (root / "scenario.yaml").read_text().replace("origin: null", "origin: {lat: 48.14, lon: 11.57}")
    (root / "scenario.yaml").write_text(text)
    scenario = load_scenario(root)
    table = pd.DataFrame({"round": 1, "cell_id": [11, 12, 11], "grid_id": [102, 100, 100], "rsrp_dbm": [-90.0] * 3})
    out = with_grid_positions(table, scenario)
    assert list(out.columns) == ["round", "cell_id", "grid_id", "x", "y", "lat", "lon", "rsrp_dbm"]
    assert out["x"].tolist() == [10.0, 50.0, 50.0] and out["y"].tolist() == [-95.0, 80.0, 80.0]
    back = geodetic_to_enu(out["lat"].to_numpy(), out["lon"].to_numpy(), np.zeros(3), MUNICH)
    np.testing.assert_allclose(back[:, :2], out[["x", "y"]].to_numpy(), atol=1e-6)
    plain = with_grid_positions(
        table, dataclasses.replace(scenario, meta=dataclasses.replace(scenario.meta, origin=None))
    )
    assert "lat" not in plain.columns and "x" in plain.columns  # no real place: metres only


def test_maps_sit_above_eval_and_network_and_below_the_cli() -> None:
    import subprocess
    import sys

    code = (
        "import sys, rflscm.eval, rflscm.network; assert 'rflscm.maps' not in sys.modules; "
        "import rflscm.maps; print(sorted({m.split('.')[1] for m in sys.modules if m.startswith('rflscm.')}))"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    assert "'cli'" not in run.stdout and "'bench'" not in run.stdout and "'maps'" in run.stdout
