"""Tiled models end to end (issue 29): `train --tile-sites`, then predict / evaluate / map / optimize read the tiled
checkpoint as one network; WNOMP in tiles answers exactly what the whole answers (the halo carries the SS-SINR
interference); a damaged manifest is one line; serial and 2-worker Ray tile training give the same model."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
import yaml

from rflscm.data import load_scenario
from rflscm.geometry import AngleGrid
from rflscm.models import load_model
from rflscm.models.base import CHECKPOINT_FORMAT, content_hash, read_checkpoint, to_plain
from rflscm.models.tiled import TiledModel
from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario

GRID = AngleGrid(num_el=31, num_az=36, el_min_deg=-90.0, el_step_deg=6.0)
TINY = (
    "prior: {enabled: false}\nfield: {voxel_m: 20.0, delta_rank: 2, feature_rank: 2, feature_dim: 4}\n"
    "decoder: {hidden: 8}\nrender: {step_m: 8.0}\nhitam: {top_k: 2, warmup_steps: 4, ramp_steps: 2}\n"
    "train: {steps: 6, batch_pairs: 4, val_pairs: 2, val_every: 3}\n"
    "corrections: {pair_anchors: false, pair_posterior: false}\n"
)


def rflscm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rflscm.cli", "--threads", "1", *args], capture_output=True, text=True, timeout=600
    )


@pytest.fixture(scope="module")
def network(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """Three sites (18 cells) in the field regime (SS-SINR reporting), whole and tiled (one site a tile) WNOMP."""
    root = tmp_path_factory.mktemp("tiles")
    config = SimulationConfig(
        num_sites=3,
        max_grids=40,
        seed=4,
        site_radius_m=120.0,
        angle_grid=GRID,
        point_cloud_points_per_m2=0.05,
        measurements="field",
    )
    build_scenario(ProceduralCity(seed=3, size_m=300.0, num_buildings=12), config, root / "s", progress=False)
    whole, tiled = root / "whole.ckpt", root / "tiled.ckpt"
    for out, tiles in ((whole, "0"), (tiled, "1")):
        run = rflscm("train", str(root / "s"), "--model", "wnomp", "--tile-sites", tiles, "--out", str(out))
        assert run.returncode == 0, run.stderr
        if tiles == "1":
            text = " ".join(run.stderr.split())
            assert "in tiles of about 1 sites (in turn)" in text
            assert "tile 1/3: sites" in text and "tile 3/3: sites" in text and "training pairs" in text
            assert f"wrote {out} (3 tiles, 18 cells)" in text
    return root / "s", whole, tiled


def test_a_tiled_checkpoint_is_one_file_that_loads_as_one_network(network) -> None:
    scenario_dir, _, tiled = network
    scenario = load_scenario(scenario_dir)
    model = load_model(tiled, scenario)  # the full scenario's fingerprint
    assert isinstance(model, TiledModel) and len(model.tiles) == 3 and not model.supports_unseen_grids
    manifest = model.manifest()
    assert [t["model"] for t in manifest["tiles"]] == ["wnomp"] * 3
    assert sorted(c for t in manifest["tiles"] for c in t["cells"]) == scenario.cell_ids().tolist()
    assert sorted(s for t in manifest["tiles"] for s in t["sites"]) == [1, 2, 3]
    assert model.run_info["tiling"]["tiles"] == 3 and model.run_info["protocol"]["name"] == "adjust"
    for tile in model.tiles:  # each tile keeps the fingerprint of its own part
        assert tile.fingerprint != model.fingerprint and tile.run_info["tile"]["cells"] == 6
    torch.load(tiled, weights_only=True)  # tensors, numbers and text only


def test_tiled_wnomp_predicts_exactly_what_the_whole_network_predicts(network, tmp_path) -> None:
    scenario_dir, whole, tiled = network
    tables = {}
    for name, ckpt in (("whole", whole), ("tiled", tiled)):
        out = tmp_path / f"{name}.csv"
        run = rflscm("predict", str(ckpt), str(scenario_dir), "--round", "2", "--pairs", "measured", "--out", str(out))
        assert run.returncode == 0, run.stderr
        tables[name] = pd.read_csv(out)
    assert len(tables["whole"]) > 500
    pd.testing.assert_frame_equal(tables["tiled"], tables["whole"], check_exact=True)


def test_evaluate_map_and_optimize_read_the_tiled_model(network, tmp_path) -> None:
    scenario_dir, whole, tiled = network
    metrics, summaries = {}, {}
    small = ["--tilt-range", "0:4:2", "--elec-tilt-range", "0:0", "--azimuth-range", "0:0", "--restarts", "0"]
    for name, ckpt in (("whole", whole), ("tiled", tiled)):
        run = rflscm("evaluate", str(ckpt), str(scenario_dir), "--json", str(tmp_path / f"{name}.json"))
        assert run.returncode == 0, run.stderr
        metrics[name] = json.loads((tmp_path / f"{name}.json").read_text())
        run = rflscm("optimize", str(ckpt), str(scenario_dir), "--out", str(tmp_path / f"o_{name}"), *small)
        assert run.returncode == 0, run.stderr
        summaries[name] = json.loads((tmp_path / f"o_{name}" / "summary.json").read_text())
    assert metrics["tiled"]["mae_db"] == metrics["whole"]["mae_db"]
    assert metrics["tiled"]["per_cell"] == metrics["whole"]["per_cell"]
    assert metrics["tiled"]["model"]["name"] == "tiled"
    for key in ("changed_cells", "best"):
        if key in summaries["whole"]:
            assert summaries["tiled"][key] == summaries["whole"][key]
    run = rflscm("map", str(tiled), str(scenario_dir), "--round", "2", "--out", str(tmp_path / "m"), "--no-html")
    assert run.returncode == 0, run.stderr
    assert any((tmp_path / "m").iterdir())


def test_a_damaged_manifest_is_refused_in_one_line(network, tmp_path) -> None:
    scenario_dir, _, tiled = network
    payload = to_plain(read_checkpoint(tiled))
    payload.pop("format")
    tiles = payload["state"]["manifest"]["tiles"]
    tiles[1]["cells"] = tiles[1]["cells"] + tiles[0]["cells"][:1]  # one cell in two tiles, the hash made to agree
    bad = tmp_path / "bad.ckpt"
    torch.save({"format": CHECKPOINT_FORMAT, "sha256": content_hash(payload), "payload": payload}, bad)
    run = rflscm("predict", str(bad), str(scenario_dir), "--out", str(tmp_path / "p.csv"))
    lines = run.stderr.strip().splitlines()
    assert run.returncode == 2 and "Traceback" not in run.stderr and len(lines) == 1, run.stderr
    assert lines[0].startswith("CheckpointError: ") and "to 2 tiles" in lines[0]
    tiles[1]["model"] = "tiled"  # a tile that is itself tiled
    torch.save({"format": CHECKPOINT_FORMAT, "sha256": content_hash(payload), "payload": payload}, bad)
    run = rflscm("predict", str(bad), str(scenario_dir), "--out", str(tmp_path / "p.csv"))
    assert (
        run.returncode == 2 and len(run.stderr.strip().splitlines()) == 1 and "tile 1 of the tiled model" in run.stderr
    )


def test_tiling_options_are_checked_in_one_line(network, tmp_path) -> None:
    scenario_dir, _, tiled = network
    run = rflscm("train", str(scenario_dir), "--model", "wnomp", "--workers", "2", "--out", str(tmp_path / "w.ckpt"))
    assert run.returncode == 2 and "give --tile-sites K as well" in run.stderr and "Traceback" not in run.stderr
    run = rflscm("train", str(scenario_dir), "--tile-sites", "1", "--resume", "--out", str(tiled))
    assert run.returncode == 2 and "--resume does not apply to a tiled model" in run.stderr
    out = tmp_path / "w.ckpt"
    run = rflscm(
        "train", str(scenario_dir), "--model", "wnomp", "--tile-sites", "1", "--minutes", "1", "--out", str(out)
    )
    assert run.returncode == 0 and "note: --minutes does not apply to wnomp" in " ".join(run.stderr.split())


@pytest.mark.slow
def test_serial_and_two_ray_workers_train_the_same_tiled_rflscm(network, tmp_path, one_thread) -> None:
    pytest.importorskip("ray")
    from rflscm.eval.protocols import AdjustProtocol
    from rflscm.parallel.engine import Engine
    from rflscm.parallel.tiles import ray_runner
    from rflscm.train.tiles import fit_tiled

    scenario = load_scenario(network[0])
    config = yaml.safe_load(TINY)
    lines: dict[str, list[str]] = {"serial": [], "ray": []}
    models = {
        name: fit_tiled(
            "rflscm",
            config,
            scenario,
            AdjustProtocol(),
            2,
            angle_grid=GRID,
            runner=runner,
            report=lines[name].append,
            progress=False,
        )
        for name, runner in (("serial", None), ("ray", ray_runner(Engine(workers=2))))
    }
    for found in lines.values():  # one line per tile (in the order they end)
        assert sorted(line.split(":")[0] for line in found) == ["tile 1/2", "tile 2/2"]
        assert all("cells" in line and "training pairs" in line for line in found)
    serial, ray = models["serial"], models["ray"]
    assert len(serial.tiles) == 2 and serial.supports_unseen_grids
    for a, b in zip(serial.tiles, ray.tiles, strict=True):  # every weight, bit for bit
        assert content_hash(to_plain(a.state_dict_for_checkpoint())) == content_hash(
            to_plain(b.state_dict_for_checkpoint())
        )
    cells, grids = np.meshgrid(scenario.cell_ids(), scenario.grid_ids(), indexing="ij")
    assert torch.equal(serial.aps(cells.ravel(), grids.ravel()), ray.aps(cells.ravel(), grids.ravel()))
    serial.save(tmp_path / "serial.ckpt")
    loaded = load_model(tmp_path / "serial.ckpt", scenario)
    assert torch.equal(loaded.aps(cells.ravel(), grids.ravel()), serial.aps(cells.ravel(), grids.ravel()))
