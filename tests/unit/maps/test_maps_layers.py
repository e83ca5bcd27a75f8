"""KPI layers and files of a scenario without an origin: per-cell popup values agree with the KPI layers, the
layers with the prediction path, and every file states that the position on Earth is nominal."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.errors import ConfigError
from rflscm.eval import fit_with_protocol
from rflscm.eval.cache import APSCache
from rflscm.geometry import AngleGrid
from rflscm.maps import map_pairs, round_layers, write_layers
from rflscm.models import MODEL_REGISTRY
from rflscm.network.kpi import KPIConfig

GRID = AngleGrid(num_el=31, num_az=36, el_min_deg=-90.0, el_step_deg=6.0)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory):
    scenario = load_scenario(tiny_scenario(tmp_path_factory.mktemp("maps") / "tiny", seed=5))
    model = MODEL_REGISTRY["wnomp"].build(None, GRID, "cpu")
    fit_with_protocol(model, scenario, None, progress=False)
    return scenario, APSCache(model)


def test_layers_agree_with_the_prediction_path_and_with_themselves(fitted) -> None:
    scenario, cache = fitted
    cfg = KPIConfig(threshold_dbm=-95.0)
    layers = round_layers(cache, scenario, 2, cfg)
    pairs = map_pairs(scenario, cache)
    rsrp = cache.predict_rsrp(scenario, 2, "ssb", pairs)
    grid_pos = np.searchsorted(scenario.grid_ids(), pairs["grid_id"].to_numpy())
    assert [c.freq_hz for c in layers.carriers] == [2.1e9, 3.5e9]
    for c in layers.carriers:
        mine = np.isin(pairs["cell_id"].to_numpy(), c.cell_ids)
        for g in range(len(scenario.grid_ids())):
            rows = np.flatnonzero(mine & (grid_pos == g))
            if not rows.size:
                assert np.isnan(c.rsrp_dbm[g]) and c.serving[g] == -1
                continue
            best = np.nanmax(rsrp[rows], axis=1)
            assert abs(c.rsrp_dbm[g] - best.max()) < 1e-9
            assert c.serving[g] == pairs["cell_id"].to_numpy()[rows[np.argmax(best)]]
            server = int(np.flatnonzero(c.cell_ids == c.serving[g])[0])
            assert abs(c.cell_sinr_db[server, g] - c.sinr_db[g]) < 1e-6  # the popup's serving row = the SINR layer
            assert abs(c.cell_rsrp_dbm[server, g] - c.rsrp_dbm[g]) < 1e-6
            assert c.covered[g] == float(c.rsrp_dbm[g] >= -95.0)


def test_files_of_a_scenario_without_origin_say_the_position_is_nominal(fitted, tmp_path: Path) -> None:
    import rasterio

    scenario, cache = fitted
    assert scenario.meta.origin is None
    out = write_layers(cache, scenario, tmp_path / "m", 1, html=False)
    names = {p.name for p in out.files}
    assert "map.html" not in names and {"rsrp_round1.tif", "grids.geojson", "map.kml"} <= names
    doc = json.loads((tmp_path / "m" / "grids.geojson").read_text())
    assert doc["nominal_origin"] is True and "NOMINAL" in doc["crs_note"]
    assert "NOMINAL" in (tmp_path / "m" / "map.kml").read_text()
    with rasterio.open(tmp_path / "m" / "rsrp_round1.tif") as ds:
        assert "NOMINAL" in ds.tags()["CRS_NOTE"] and ds.crs.to_dict()["lat_0"] == 0.0
    with pytest.raises(ConfigError, match="--compare-round 1 is --round itself"):
        write_layers(cache, scenario, tmp_path / "x", 1, 1)


def test_a_field_model_maps_every_pair_and_its_html_has_an_aps_per_served_grid(fitted, tmp_path: Path) -> None:
    import torch

    scenario, _ = fitted
    config = {
        "prior": {"enabled": False},
        "field": {"voxel_m": 20.0, "delta_rank": 2, "feature_rank": 2, "feature_dim": 4},
        "decoder": {"hidden": 16},
        "render": {"step_m": 8.0},
        "hitam": {"top_k": 3, "warmup_steps": 4, "ramp_steps": 2},
        "train": {"steps": 4, "batch_pairs": 4, "pairs_per_cell": 2, "val_pairs": 2, "val_every": 2},
    }
    torch.manual_seed(0)
    model = MODEL_REGISTRY["rflscm"].build(
        config, AngleGrid(num_el=16, num_az=18, el_min_deg=-90.0, el_step_deg=12.0), "cpu"
    )
    fit_with_protocol(model, scenario, None, progress=False)
    out = write_layers(model, scenario, tmp_path / "m", 1, 2)
    assert out.layers[0].pairs == "every (cell, grid) pair"
    served = {
        (int(s), int(g))
        for lay in out.layers
        for c in lay.carriers
        for s, g in zip(c.serving, scenario.grid_ids())
        if s >= 0
    }
    html = (tmp_path / "m" / "map.html").read_text()
    start = html.index("const D = ") + len("const D = ")
    data = json.loads(html[start : html.index(";\n", start)])
    assert set(data["aps"]) == {f"{s}:{g}" for s, g in served} and all(
        v.startswith("data:image/png;base64,") for v in data["aps"].values()
    )
    assert len(data["overlays"]) == 2 * 2 * 4 + 2 * 3 and all(len(o["colours"]) == 3 for o in data["overlays"])
