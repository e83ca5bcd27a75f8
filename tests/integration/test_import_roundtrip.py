"""Issue 25, deliverable 5: simulate → raw samples and cell list → `rflscm import` → the simulator's scenario back."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from rflscm.data import load_scenario
from rflscm.data.geo import geodetic_to_enu

pytestmark = pytest.mark.slow

SAMPLES, FADING_DB = 8, 2.0


def rflscm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rflscm.cli", *args], capture_output=True, text=True, timeout=300)


def test_simulate_raw_then_import_gives_the_scenario_back(tmp_path: Path) -> None:
    config = tmp_path / "sim.yaml"
    config.write_text(
        "site_radius_m: 100\npoint_cloud_points_per_m2: 0.05\n"
        "angle_grid: {num_el: 31, num_az: 36, el_min_deg: -90, el_step_deg: 6}\n"
        "backend_options: {size_m: 220, num_buildings: 10}\n"
    )
    sim, raw, imported = tmp_path / "sim", tmp_path / "raw", tmp_path / "imported"
    run = rflscm(
        "simulate",
        "--backend",
        "procedural",
        "--scene",
        "city",
        "--sites",
        "2",
        "--grids",
        "30",
        "--carriers",
        "3.5e9,2.1e9",
        "--seed",
        "3",
        "--config",
        str(config),
        "--out",
        str(sim),
        "--device",
        "cpu",
        "--raw-out",
        str(raw),
        "--raw-samples",
        str(SAMPLES),
        "--raw-fading",
        str(FADING_DB),
    )
    assert run.returncode == 0, run.stderr
    assert "wrote raw" in run.stderr
    run = rflscm("import", str(raw / "import.yaml"), "--out", str(imported), "--format", "csv")
    assert run.returncode == 0, run.stderr
    assert "kept" in run.stdout and "samples kept and dropped" in run.stdout
    check = rflscm("check", str(imported))
    assert check.returncode == 0, check.stderr
    text = " ".join(check.stdout.split())  # Rich wraps lines
    assert "needs a point cloud" not in text  # --raw-out wrote it beside the samples, import.yaml names it

    truth, got = load_scenario(sim), load_scenario(imported)
    assert got.point_cloud is not None and got.point_cloud == truth.point_cloud
    raw_samples = pd.read_csv(raw / "samples.csv")
    # cells: lat/lon written from one origin and projected back by the importer: the same positions
    np.testing.assert_allclose(got.cells[1][["x", "y", "z"]], truth.cells[1][["x", "y", "z"]], rtol=0, atol=1e-6)
    assert got.cells[1]["cell_id"].tolist() == truth.cells[1]["cell_id"].tolist()
    for col in ("azimuth_deg", "mech_tilt_deg", "elec_tilt_deg", "freq_hz", "ssb_codebook", "csi_codebook"):
        assert got.cells[2][col].tolist() == truth.cells[2][col].tolist(), col
    # every sample's lat/lon projects back inside its grid's square: the same grids at the same centres
    xyz = geodetic_to_enu(raw_samples["lat"], raw_samples["lon"], raw_samples["height_m"], got.meta.origin)
    assert np.isfinite(xyz).all()
    grids = got.grids.merge(truth.grids, on=["x", "y", "z"], suffixes=("", "_sim"))
    assert len(grids) == len(got.grids) == truth.measurements.dropna()["grid_id"].nunique()
    # values: each imported bin is the linear mean of SAMPLES fading draws around the simulator's value
    m = got.measurements.merge(grids[["grid_id", "grid_id_sim"]], on="grid_id")
    m = m.drop(columns="grid_id").rename(columns={"grid_id_sim": "grid_id"})
    both = m.merge(
        truth.measurements, on=["round", "cell_id", "grid_id", "beam_type", "beam_id"], suffixes=("", "_sim")
    )
    assert len(both) == len(m) == truth.measurements["rsrp_dbm"].notna().sum()  # nothing lost, nothing invented
    diff = both["rsrp_dbm"] - both["rsrp_dbm_sim"]
    spread = FADING_DB / np.sqrt(SAMPLES)  # σ of the mean of SAMPLES log-normal draws, ≈ 0.71 dB
    assert abs(diff.mean()) < 0.5 * spread
    assert 0.5 * spread < diff.std() < 1.5 * spread
    assert diff.abs().max() < 6 * spread  # the worst of ~26k bins: a 6σ bin would be a 1-in-20 000 event
    bins = pd.read_csv(imported / "import_bins.csv")
    assert int(bins["samples"].sum()) + sum(got.meta.simulation["import"]["dropped"].values()) == len(raw_samples)
    assert bins["std_db"].median() == pytest.approx(FADING_DB, rel=0.25)


def test_shipped_example_imports_with_its_point_cloud(tmp_path: Path) -> None:
    # docs/your-own-data.md starts here: the default RF-LSCM needs the cloud, so the example must carry it
    import rflscm as package

    example = Path(package.__file__).parent / "assets" / "examples" / "raw"
    run = rflscm("import", str(example / "import.yaml"), "--out", str(tmp_path / "my-network"))
    assert run.returncode == 0, run.stderr
    assert "no point cloud" not in run.stdout
    got = load_scenario(tmp_path / "my-network")
    assert got.meta.point_cloud == "point_cloud.laz" and got.point_cloud is not None
    assert len(got.grids) == 28 and len(got.cells[1]) == 42 and got.rounds() == [1, 2]
