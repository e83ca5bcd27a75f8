"""`rflscm map` end to end on a small trained checkpoint: GeoTIFF, GeoJSON and KML read back (rasterio, json,
xml) with the scenario's CRS and values equal to `rflscm predict`'s, and the offline HTML map in a real
browser (Debian's chromium through playwright, network off)."""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from rflscm.data import load_scenario
from rflscm.data.geo import Origin, enu_to_geodetic
from rflscm.eval import fit_with_protocol
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY
from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario

pytestmark = pytest.mark.slow
GRID = AngleGrid(num_el=31, num_az=36, el_min_deg=-90.0, el_step_deg=6.0)
ORIGIN = Origin(lat=48.14, lon=11.57)
CHROMIUM = Path("/usr/bin/chromium")


def rflscm(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", "rflscm.cli", "--threads", "1", *args],
        capture_output=True,
        text=True,
        timeout=600,
        env=env,
    )


@pytest.fixture(scope="module")
def mapped(tmp_path_factory: pytest.TempPathFactory):
    """A procedural 2-site scenario with a real origin, a WNOMP checkpoint, its maps of rounds 1 and 2 and
    `predict`'s round-2 table."""
    base = tmp_path_factory.mktemp("map")
    root = base / "sc"
    config = SimulationConfig(
        num_sites=2, max_grids=40, seed=5, site_radius_m=120.0, angle_grid=GRID, point_cloud_points_per_m2=0.05
    )
    build_scenario(ProceduralCity(seed=3, size_m=240.0, num_buildings=12), config, root, progress=False)
    scenario = load_scenario(root)
    model = MODEL_REGISTRY["wnomp"].build(None, GRID, "cpu")
    fit_with_protocol(model, scenario, None, progress=False)
    ckpt = model.save(base / "w.ckpt")
    # georeference the scenario after training: the checkpoint stays valid (the origin is not in the fingerprint)
    text = (root / "scenario.yaml").read_text()
    (root / "scenario.yaml").write_text(
        text.replace("origin: null", f"origin: {{lat: {ORIGIN.lat}, lon: {ORIGIN.lon}}}")
    )
    scenario = load_scenario(root)
    assert scenario.meta.origin == ORIGIN
    out = base / "maps"
    run = rflscm(
        "map", str(ckpt), str(root), "--round", "1", "--compare-round", "2", "--out", str(out), "--device", "cpu"
    )
    assert run.returncode == 0, run.stderr
    pred = base / "pred.csv"
    run2 = rflscm(
        "predict", str(ckpt), str(root), "--round", "2", "--pairs", "measured", "--out", str(pred), "--device", "cpu"
    )
    assert run2.returncode == 0, run2.stderr
    return scenario, out, pd.read_csv(pred), run.stderr


def best_server(scenario, pred: pd.DataFrame) -> dict[float, pd.DataFrame]:
    """Per carrier: best-server RSRP and serving cell per grid, from `predict`'s SSB rows."""
    ssb = pred[pred["beam_type"] == "ssb"]
    freq = scenario.cells[1].set_index("cell_id")["freq_hz"]
    best = ssb.groupby(["cell_id", "grid_id"], as_index=False)["rsrp_dbm"].max()
    best["freq_hz"] = freq.loc[best["cell_id"]].to_numpy()
    out = {}
    for f, group in best.groupby("freq_hz"):
        top = group.sort_values("rsrp_dbm", ascending=False).drop_duplicates("grid_id").set_index("grid_id")
        out[float(f)] = top
    return out


def _band_stack(path: Path) -> np.ndarray:
    import rasterio

    with rasterio.open(path) as ds:
        return ds.read()


def test_geotiffs_have_the_scenario_crs_and_predicts_values(mapped) -> None:
    import rasterio

    scenario, out, pred, _ = mapped
    grids = scenario.grids.set_index("grid_id")
    expected = best_server(scenario, pred)
    with rasterio.open(out / "rsrp_round2.tif") as ds, rasterio.open(out / "serving_cell_round2.tif") as sv:
        crs = ds.crs.to_dict()
        assert crs["proj"] == "tmerc" and crs["lat_0"] == ORIGIN.lat and crs["lon_0"] == ORIGIN.lon
        assert "48.14" in ds.tags()["CRS_NOTE"] and ds.tags()["UNIT"] == "dBm"
        assert ds.res == (10.0, 10.0)  # the simulator's 10 m grid, detected from the spacing
        carriers = sorted(expected)
        assert list(ds.descriptions) == [f"{f / 1e9:g} GHz" for f in carriers]
        rsrp, serving = ds.read(), sv.read()
        for band, f in enumerate(carriers):
            top = expected[f]
            rows, cols = rasterio.transform.rowcol(ds.transform, grids.loc[top.index, "x"], grids.loc[top.index, "y"])
            np.testing.assert_allclose(rsrp[band, rows, cols], top["rsrp_dbm"].to_numpy(), atol=1e-3)
            assert serving[band, rows, cols].tolist() == top["cell_id"].tolist()
            assert np.isfinite(rsrp[band]).sum() == len(top)  # nodata everywhere else
            assert (serving[band] >= 0).sum() == len(top)
    diff, r1, r2 = (
        _band_stack(out / f) for f in ("rsrp_diff_round2_minus_round1.tif", "rsrp_round1.tif", "rsrp_round2.tif")
    )
    np.testing.assert_allclose(diff, r2 - r1, atol=1e-3, equal_nan=True)
    with rasterio.open(out / "coverage_round2.tif") as cov:
        assert cov.nodata == 255 and set(np.unique(cov.read())) <= {0, 1, 255}
        np.testing.assert_array_equal(cov.read() == 1, rsrp >= -105.0)


def test_geojson_is_wgs84_with_local_xy_and_predicts_values(mapped) -> None:
    scenario, out, pred, _ = mapped
    doc = json.loads((out / "grids.geojson").read_text())
    assert "48.14" in doc["crs_note"] and doc["nominal_origin"] is False and doc["pixel_size_m"] == 10.0
    assert len(doc["features"]) == len(scenario.grids)
    expected = best_server(scenario, pred)
    for feature in doc["features"]:
        p = feature["properties"]
        ring = np.array(feature["geometry"]["coordinates"][0])
        lat, lon, _ = enu_to_geodetic(np.array([[p["x"], p["y"], 0.0]]), ORIGIN)
        assert abs(p["lat"] - lat[0]) < 1e-9 and abs(p["lon"] - lon[0]) < 1e-9
        assert abs(ring[:4, 0].mean() - lon[0]) < 1e-7 and abs(ring[:4, 1].mean() - lat[0]) < 1e-7  # lon, lat order
        for f, top in expected.items():
            key = f"r2_{f / 1e9:g}GHz_rsrp_dbm"
            if p["grid_id"] in top.index:
                assert abs(p[key] - top.loc[p["grid_id"], "rsrp_dbm"]) < 1e-9
                assert p[f"r2_{f / 1e9:g}GHz_serving_cell"] == top.loc[p["grid_id"], "cell_id"]
            else:
                assert p[key] is None
    cells = json.loads((out / "cells.geojson").read_text())["features"]
    assert {c["properties"]["round"] for c in cells} == {1, 2}
    changed = {c["properties"]["cell_id"] for c in cells if c["properties"]["changed"]}
    c1, c2 = scenario.cells[1].set_index("cell_id"), scenario.cells[2].set_index("cell_id")
    truly = {
        int(i)
        for i in c1.index
        if not c1.loc[i, ["azimuth_deg", "mech_tilt_deg", "elec_tilt_deg", "ssb_codebook", "csi_codebook"]].equals(
            c2.loc[i, ["azimuth_deg", "mech_tilt_deg", "elec_tilt_deg", "ssb_codebook", "csi_codebook"]]
        )
    }
    assert changed == truly and changed
    points = json.loads((out / "measured.geojson").read_text())["features"]
    measured = scenario.measurements[scenario.measurements["round"] == 1]["grid_id"].unique()
    assert {p["properties"]["grid_id"] for p in points if p["properties"]["round"] == 1} == set(measured.tolist())


def test_kml_and_predict_table_carry_the_geography(mapped) -> None:
    scenario, out, pred, stderr = mapped
    ns = {"k": "http://www.opengis.net/kml/2.2"}
    doc = ET.parse(out / "map.kml").getroot().find("k:Document", ns)
    assert "48.14" in doc.find("k:description", ns).text
    folders = doc.findall("k:Folder", ns)
    names = [f.find("k:name", ns).text for f in folders]
    assert sum("best-server SSB RSRP" in n for n in names) == 4  # 2 rounds × 2 carriers
    first = folders[0].findall("k:Placemark", ns)
    assert len(first) == len(scenario.grids)
    lon, lat, _ = (float(v) for v in first[0].find(".//k:coordinates", ns).text.split()[0].split(","))
    assert abs(lat - ORIGIN.lat) < 0.05 and abs(lon - ORIGIN.lon) < 0.05
    # `predict`: grid positions beside the grid ids
    assert list(pred.columns[:7]) == ["round", "cell_id", "grid_id", "x", "y", "lat", "lon"]
    g = scenario.grids.set_index("grid_id").loc[pred["grid_id"]]
    np.testing.assert_array_equal(pred["x"].to_numpy(), g["x"].to_numpy())
    assert "48.14" in " ".join(stderr.split())


def test_map_refuses_bad_rounds_in_one_line(mapped, tmp_path) -> None:
    scenario, out, _, _ = mapped
    ckpt = out.parent / "w.ckpt"
    for args in (["--round", "7"], ["--round", "2", "--compare-round", "2"]):
        run = rflscm("map", str(ckpt), str(scenario.root), *args, "--out", str(tmp_path / "m"), "--device", "cpu")
        assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1, run.stderr
        assert run.stderr.startswith("ConfigError: --")


def test_map_never_writes_over_its_inputs_and_checks_its_numbers(mapped, tmp_path) -> None:
    scenario, out, _, _ = mapped
    ckpt = out.parent / "w.ckpt"
    before = sorted(p.name for p in scenario.root.iterdir())
    yaml_text = (scenario.root / "scenario.yaml").read_text()
    run = rflscm("map", str(ckpt), str(scenario.root), "--out", str(scenario.root / "scenario.yaml"), "--device", "cpu")
    assert run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1, run.stderr
    assert sorted(p.name for p in scenario.root.iterdir()) == before  # nothing written or replaced
    assert (scenario.root / "scenario.yaml").read_text() == yaml_text
    run = rflscm("map", str(ckpt), str(scenario.root), "--out", str(ckpt), "--device", "cpu")
    assert run.returncode == 2 and ckpt.stat().st_size > 0, run.stderr
    run = rflscm("map", str(ckpt), str(scenario.root), "--threshold", "nan", "--out", str(tmp_path / "m"))
    assert run.returncode == 2 and "--threshold" in run.stderr and len(run.stderr.strip().splitlines()) == 1


@pytest.mark.skipif(not CHROMIUM.exists(), reason="Debian's chromium is not installed (.ci/run installs it)")
def test_html_map_works_offline_in_a_real_browser(mapped, tmp_path) -> None:
    from playwright.sync_api import sync_playwright

    _, out, _, _ = mapped
    html = (out / "map.html").read_text()
    assert "<script src=" not in html and '<link rel="stylesheet" href="http' not in html
    attempted: list[str] = []

    def route(r) -> None:
        url = r.request.url
        if url.startswith(("file:", "data:", "about:")):
            r.continue_()
        else:
            attempted.append(url)
            r.abort()

    with sync_playwright() as p:
        ctx = p.chromium.launch_persistent_context(
            str(tmp_path / "profile"),
            executable_path=str(CHROMIUM),
            headless=True,
            args=[
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
            ],
        )
        try:
            ctx.route("**/*", route)
            page = ctx.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda e: errors.append(str(e)))
            page.goto((out / "map.html").as_uri())
            page.wait_for_selector("path.rflscm-grid")
            assert errors == [] and attempted == []
            shot = np.frombuffer(page.screenshot(type="jpeg", quality=90), np.uint8)
            labels = [t.strip() for t in page.locator(".leaflet-control-layers-overlays label").all_inner_texts()]
            data = page.evaluate("window.rflscmData.overlays.map(o => o.name)")
            assert labels[: len(data)] == data and len(data) == 2 * 2 * 4 + 2 * 3  # rounds × carriers × KPIs + diffs
            assert "cells · round 2 (red: changed)" in labels and "measured grids" in labels
            legend = page.locator(".rflscm-legend").inner_text()
            assert "(dBm)" in legend and "(dB)" in legend
            # click a grid square whose centre is not under a cell wedge
            point = page.evaluate("""() => {
                for (const el of document.querySelectorAll('path.rflscm-grid')) {
                    const b = el.getBoundingClientRect(); const x = b.x + b.width / 2, y = b.y + b.height / 2;
                    if (document.elementFromPoint(x, y) === el) return [x, y];
                }
                return null; }""")
            assert point is not None
            page.mouse.click(*point)
            popup = page.wait_for_selector(".leaflet-popup-content .rflscm-popup")
            text = popup.inner_text()
            assert "RSRP (dBm)" in text and "SINR (dB)" in text and "(serving)" in text
            assert page.locator(".leaflet-popup-content img.rflscm-aps").count() == 1
            assert attempted == []
        finally:
            ctx.close()
    pixels = np.asarray(Image.open(io.BytesIO(shot.tobytes())).convert("L"), np.float64)
    assert pixels.std() > 10.0  # not a blank page


def test_optimize_maps_writes_the_before_after_layers(mapped, tmp_path) -> None:
    import rasterio

    scenario, out, _, _ = mapped
    opt = tmp_path / "opt"
    run = rflscm(
        "optimize",
        str(out.parent / "w.ckpt"),
        str(scenario.root),
        "--out",
        str(opt),
        "--tilt-range",
        "0:6:2",
        "--azimuth-range",
        "-5:5:5",
        "--max-changed",
        "2",
        "--restarts",
        "0",
        "--no-verify",
        "--maps",
        "--device",
        "cpu",
    )
    assert run.returncode == 0, run.stderr
    maps = opt / "maps"
    for name in (
        "rsrp_round1.tif",
        "rsrp_round3.tif",
        "rsrp_diff_round3_minus_round1.tif",
        "grids.geojson",
        "cells.geojson",
        "map.kml",
        "map.html",
    ):
        assert (maps / name).is_file(), name
    changes = pd.read_csv(opt / "changes.csv")
    assert len(changes) > 0  # seeded: the search changes cells here, so the check below is not vacuous
    cells = json.loads((maps / "cells.geojson").read_text())["features"]
    flagged = {c["properties"]["cell_id"] for c in cells if c["properties"]["changed"]}
    assert flagged == set(changes["cell_id"].tolist())
    with rasterio.open(maps / "rsrp_round3.tif") as ds:
        assert ds.crs.to_dict()["lat_0"] == ORIGIN.lat


def test_map_of_the_shipped_scenario_is_in_munich_and_equals_predict(tmp_path) -> None:
    import rasterio

    from rflscm.sim import default_scenario_path

    root = default_scenario_path()
    ckpt = tmp_path / "w.ckpt"
    assert rflscm("train", str(root), "--model", "wnomp", "--out", str(ckpt), "--no-progress").returncode == 0
    run = rflscm(
        "map", str(ckpt), str(root), "--round", "2", "--out", str(tmp_path / "m"), "--no-html", "--device", "cpu"
    )
    assert run.returncode == 0, run.stderr
    pred = tmp_path / "p.parquet"
    run = rflscm("predict", str(ckpt), str(root), "--round", "2", "--out", str(pred), "--device", "cpu")
    assert run.returncode == 0, run.stderr
    scenario = load_scenario(root)
    expected = best_server(scenario, pd.read_parquet(pred))
    grids = scenario.grids.set_index("grid_id")
    with rasterio.open(tmp_path / "m" / "rsrp_round2.tif") as ds:
        crs = ds.crs.to_dict()
        assert crs["proj"] == "tmerc" and (crs["lat_0"], crs["lon_0"]) == (48.14, 11.57) and ds.res == (10.0, 10.0)
        image = ds.read()
        for band, f in enumerate(sorted(expected)):
            top = expected[f]
            rows, cols = rasterio.transform.rowcol(ds.transform, grids.loc[top.index, "x"], grids.loc[top.index, "y"])
            np.testing.assert_allclose(image[band, rows, cols], top["rsrp_dbm"].to_numpy(), atol=1e-3)
    lon, lat = json.loads((tmp_path / "m" / "grids.geojson").read_text())["features"][0]["geometry"]["coordinates"][0][
        0
    ]
    assert 48.13 < lat < 48.15 and 11.56 < lon < 11.58  # central Munich
