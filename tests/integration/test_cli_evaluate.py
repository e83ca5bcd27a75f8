"""`rflscm evaluate` end to end on a tiny simulated scenario (and on the shipped default scenario)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from rflscm.data import load_scenario
from rflscm.eval import UnseenProtocol, fit_with_protocol
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY
from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario

pytestmark = pytest.mark.slow
GRID = AngleGrid(num_el=31, num_az=36, el_min_deg=-90.0, el_step_deg=6.0)
KEYS = ["mae_db", "oracle_mae_db", "trivial_mae_db", "per_cell", "aps", "unseen", "counts", "model", "protocol"]


def rflscm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rflscm.cli", *args], capture_output=True, text=True, timeout=600)


def _scenario(root: Path, seed: int):
    config = SimulationConfig(
        num_sites=2, max_grids=50, seed=seed, site_radius_m=120.0, angle_grid=GRID, point_cloud_points_per_m2=0.05
    )
    build_scenario(ProceduralCity(seed=3, size_m=240.0, num_buildings=12), config, root, progress=False)
    return load_scenario(root)


def _checkpoint(scenario, path: Path, protocol=None, grid: AngleGrid = GRID) -> Path:
    model = MODEL_REGISTRY["wnomp"].build(None, grid, "cpu")
    fit_with_protocol(model, scenario, protocol, progress=False)  # sets the fingerprint and the protocol
    return model.save(path)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory):
    return _scenario(tmp_path_factory.mktemp("cli_eval") / "sc", seed=4)


def test_evaluate_writes_json_and_report(tiny, tmp_path) -> None:
    ckpt = _checkpoint(tiny, tmp_path / "w.ckpt")
    run = rflscm(
        "evaluate",
        str(ckpt),
        str(tiny.root),
        "--json",
        str(tmp_path / "m.json"),
        "--report",
        str(tmp_path / "rep"),
        "--device",
        "cpu",
    )
    assert run.returncode == 0, run.stderr
    assert "MAE SSB, all cells [dB]" in run.stdout and "oracle" in run.stdout and "trivial" in run.stdout
    metrics = json.loads((tmp_path / "m.json").read_text())
    assert all(k in metrics for k in KEYS)
    for beam_type in ("ssb", "csi"):
        assert metrics["mae_db"][beam_type]["all"] < metrics["trivial_mae_db"][beam_type]["all"]
        assert metrics["oracle_mae_db"][beam_type]["all"] > 0
    report = (tmp_path / "rep" / "report.md").read_text()
    for name in ("coverage.png", "errors.png", "per_cell.png", "aps.png"):
        assert f"({name})" in report and (tmp_path / "rep" / name).stat().st_size > 10_000


def test_unseen_checkpoint_is_evaluated_with_its_split(tiny, tmp_path) -> None:
    ckpt = _checkpoint(tiny, tmp_path / "u.ckpt", UnseenProtocol(fraction=0.2, seed=2))
    run = rflscm("evaluate", str(ckpt), str(tiny.root), "--json", str(tmp_path / "u.json"), "--no-oracle")
    assert run.returncode == 0, run.stderr
    metrics = json.loads((tmp_path / "u.json").read_text())
    assert metrics["protocol"] == {"name": "unseen", "fraction": 0.2, "seed": 2}
    assert metrics["mae_db"]["ssb"]["all"] is None and "no notion of unseen grids" in run.stdout
    wrong = rflscm("evaluate", str(ckpt), str(tiny.root), "--protocol", "adjust")
    assert wrong.returncode == 2 and "trained for the 'unseen' protocol" in wrong.stderr


def test_user_mistakes_exit_2_with_one_line(tiny, tmp_path) -> None:
    ckpt = _checkpoint(tiny, tmp_path / "w.ckpt")
    other = _scenario(tmp_path / "other", seed=5)
    cases = [
        ((str(ckpt), str(other.root)), "trained on another scenario"),
        ((str(tmp_path / "missing.ckpt"), str(tiny.root)), "checkpoint file not found"),
        (
            (str(ckpt), str(tiny.root), "--protocol", "crossval"),
            "'crossval' is not one of 'adjust', 'unseen', 'multifreq'",
        ),
    ]
    for args, message in cases:
        run = rflscm("evaluate", *args)
        assert run.returncode == 2, run.stderr
        assert message in run.stderr and len(run.stderr.strip().splitlines()) == 1


def test_default_scenario(tmp_path) -> None:
    from rflscm.sim import default_scenario_path

    root = default_scenario_path()
    if not (root / "scenario.yaml").is_file():
        pytest.skip("the default scenario is not shipped in this checkout")
    scenario = load_scenario(root)
    ckpt = _checkpoint(scenario, tmp_path / "d.ckpt", grid=AngleGrid())
    run = rflscm("evaluate", str(ckpt), str(root), "--json", str(tmp_path / "d.json"))
    assert run.returncode == 0, run.stderr
    metrics = json.loads((tmp_path / "d.json").read_text())
    for beam_type in ("ssb", "csi"):
        assert metrics["mae_db"][beam_type]["all"] < metrics["trivial_mae_db"][beam_type]["all"]


def test_train_reports_passes_and_warns_when_a_run_barely_sees_its_data(tiny, tmp_path) -> None:
    config = tmp_path / "short.yaml"
    config.write_text(
        "prior: {enabled: false}\nfield: {voxel_m: 20.0, delta_rank: 2, feature_rank: 2, feature_dim: 4}\n"
        "decoder: {hidden: 8}\nrender: {step_m: 8.0}\nhitam: {top_k: 2, warmup_steps: 1, ramp_steps: 1}\n"
        "train: {steps: 2, batch_pairs: 4, val_pairs: 0}\n"
    )
    run = rflscm(
        "train",
        str(tiny.root),
        "--config",
        str(config),
        "--out",
        str(tmp_path / "r.ckpt"),
        "--no-progress",
        "--device",
        "cpu",
    )
    assert run.returncode == 0, run.stderr
    assert "expect it to underfit" in " ".join(run.stderr.split())
