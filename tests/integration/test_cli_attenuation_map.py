"""`rflscm predict --attenuation-map`: a top-down map of the learned attenuation for RF-LSCM and NeRF²
checkpoints, refused up-front (one line, exit 2) for WNOMP."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from matplotlib.image import imread

from rflscm.data import load_scenario
from rflscm.eval import fit_with_protocol
from rflscm.eval.report import learned_attenuation
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY
from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario

pytestmark = pytest.mark.slow
GRID = AngleGrid(num_el=16, num_az=18, el_min_deg=-90.0, el_step_deg=12.0)
CONFIGS = {
    "rflscm": {
        "prior": {"enabled": False},
        "field": {"voxel_m": 20.0, "delta_rank": 2, "feature_rank": 2, "feature_dim": 4},
        "decoder": {"hidden": 16},
        "render": {"step_m": 8.0},
        "hitam": {"top_k": 3, "warmup_steps": 4, "ramp_steps": 2},
        "train": {"steps": 6, "batch_pairs": 4, "pairs_per_cell": 2, "val_pairs": 2, "val_every": 3},
    },
    "nerf2": {
        "field": {"hidden": 16, "layers": 4, "skip_at": 2, "pos_freqs": 4, "feature_dim": 8},
        "decoder": {"hidden": 16, "head_hidden": 8},
        "hitam": {"enabled": False},
        "train": {"steps": 6, "batch_pairs": 8, "val_pairs": 4, "val_every": 3},
    },
    "wnomp": None,
}


def rflscm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rflscm.cli", "--threads", "1", *args], capture_output=True, text=True, timeout=600
    )


@pytest.fixture(scope="module")
def scenario(tmp_path_factory: pytest.TempPathFactory):
    cfg = SimulationConfig(
        name="att-tiny",
        num_sites=1,
        max_grids=16,
        seed=3,
        site_radius_m=60.0,
        carriers_hz=(3.5e9,),
        sector_azimuths_deg=(0.0, 180.0),
        point_cloud_points_per_m2=0.05,
        angle_grid=GRID,
    )
    out = tmp_path_factory.mktemp("att") / "scen"
    build_scenario(ProceduralCity(seed=2, size_m=160.0, num_buildings=6), cfg, out, progress=False)
    return load_scenario(out)


def _checkpoint(scenario, name: str, path: Path):
    torch.manual_seed(0)
    model = MODEL_REGISTRY[name].build(CONFIGS[name], GRID, "cpu")
    fit_with_protocol(model, scenario, None, progress=False)
    return model, model.save(path)


@pytest.mark.parametrize("name", ["rflscm", "nerf2"])
def test_attenuation_map_of_field_models(scenario, tmp_path, name: str) -> None:
    model, ckpt = _checkpoint(scenario, name, tmp_path / f"{name}.ckpt")
    png = tmp_path / "att.png"
    run = rflscm(
        "predict",
        str(ckpt),
        str(scenario.root),
        "--round",
        "1",
        "--out",
        str(tmp_path / "p.parquet"),
        "--attenuation-map",
        str(png),
        "--device",
        "cpu",
    )
    assert run.returncode == 0, run.stderr
    image = imread(png)
    assert image.shape[0] > 400 and image.shape[1] > 400 and image[..., :3].std() > 0.05
    xs, ys, db_per_m = learned_attenuation(model, cells_per_side=24, heights=6)
    lo, hi = np.asarray(model.scene.frame.box_lo), np.asarray(model.scene.frame.box_hi)
    assert db_per_m.shape == (24, 24) and np.all(np.isfinite(db_per_m)) and np.all(db_per_m >= 0)
    assert lo[0] < xs[0] < xs[-1] < hi[0] and lo[1] < ys[0] < ys[-1] < hi[1]
    # the map is the field's: scaling the loss channel's output scales the map
    stage = model.all_stages()[-1]
    point = torch.tensor([[xs[5], ys[7], 0.5 * (lo[2] + hi[2])]], dtype=torch.float32)
    with torch.no_grad():
        direct = stage.medium.loss_db(stage.fields.delta(stage.fields.encode(point))) / stage.medium.voxel_m
    assert db_per_m[7, 5] >= float(direct[0]) - 1e-6  # the strongest over height is at least the mid-height value


def test_attenuation_map_refused_for_wnomp_before_predicting(scenario, tmp_path) -> None:
    _, ckpt = _checkpoint(scenario, "wnomp", tmp_path / "w.ckpt")
    out = tmp_path / "p.parquet"
    run = rflscm(
        "predict",
        str(ckpt),
        str(scenario.root),
        "--out",
        str(out),
        "--attenuation-map",
        str(tmp_path / "att.png"),
        "--device",
        "cpu",
    )
    assert run.returncode == 2
    assert "no attenuation field" in run.stderr and len(run.stderr.strip().splitlines()) == 1
    assert not out.exists() and not (tmp_path / "att.png").exists()
