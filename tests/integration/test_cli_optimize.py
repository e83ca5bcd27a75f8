"""`rflscm optimize` end to end: new round, report, truth check, `check` round trip, `predict --kpi` match,
and one clear line + exit 2 for bad search specs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.eval import fit_with_protocol
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY
from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario

pytestmark = pytest.mark.slow
GRID = AngleGrid(num_el=31, num_az=36, el_min_deg=-90.0, el_step_deg=6.0)


def rflscm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rflscm.cli", "--threads", "1", *args], capture_output=True,
                          text=True, timeout=600)  # fmt: skip


def _checkpoint(scenario, path: Path) -> Path:
    model = MODEL_REGISTRY["wnomp"].build(None, GRID, "cpu")
    fit_with_protocol(model, scenario, None, progress=False)
    return model.save(path)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("cli_opt") / "sc"
    config = SimulationConfig(num_sites=2, max_grids=40, seed=5, site_radius_m=120.0, angle_grid=GRID,
                              point_cloud_points_per_m2=0.05)  # fmt: skip
    build_scenario(
        ProceduralCity(seed=3, size_m=240.0, num_buildings=12),
        config,
        root,
        progress=False,
    )
    scenario = load_scenario(root)
    return scenario, _checkpoint(scenario, root.parent / "w.ckpt")


def test_optimize_writes_a_round_that_checks_and_predicts_the_same_kpis(simulated, tmp_path) -> None:
    scenario, ckpt = simulated
    out = tmp_path / "opt"
    run = rflscm("optimize", str(ckpt), str(scenario.root), "--out", str(out), "--tilt-range", "0:10:2",
                 "--azimuth-range", "-10:10:5", "--max-changed", "3", "--restarts", "1", "--device", "cpu")  # fmt: skip
    assert run.returncode == 0, run.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["kpi_pairs"] == "measured round-1 pairs only"  # WNOMP
    assert "measured pairs only" in run.stderr
    assert summary["changed_cells"] <= 3
    assert summary["search"]["objective_after"] >= summary["search"]["objective_before"]
    assert set(summary["truth"]) >= {"before", "after", "note"} and "noiseless" in summary["truth"]["note"]
    report = (out / "report.md").read_text()
    assert "| coverage ratio [%] |" in report and "true gain" in report and (out / "maps_3.5GHz.png").is_file()
    rnd = summary["round"]["number"]
    assert rnd == 3
    check = rflscm("check", str(out / "scenario"))
    assert check.returncode == 0, check.stderr
    again = load_scenario(out / "scenario")
    assert sorted(again.cells) == [1, 2, 3] and again.fingerprint() == scenario.fingerprint()
    pred = rflscm("predict", str(ckpt), str(out / "scenario"), "--round", str(rnd), "--pairs", "measured",
                  "--out", str(tmp_path / "p.parquet"), "--kpi-json", str(tmp_path / "k.json"),
                  "--device", "cpu")  # fmt: skip
    assert pred.returncode == 0, pred.stderr
    kpis = json.loads((tmp_path / "k.json").read_text())
    for key in ("coverage", "mean_sinr_db", "overlap", "mean_rsrp_dbm", "p5_sinr_db"):
        assert kpis[key] == pytest.approx(summary["predicted"]["after"][key], abs=1e-4), key


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--tilt-range", "10:2"], "range reversed"),
        (["--freeze", "424242"], "unknown cell 424242"),
        (["--codebooks", "nope"], "'nope' is not a codebook of scenario.yaml"),
        (
            [
                "--tilt-range",
                "3:3",
                "--elec-tilt-range",
                "3:3",
                "--azimuth-range",
                "0:0",
                "--max-changed",
                "1",
                "--codebooks",
                "__current__",
            ],
            None,
        ),
    ],
)
def test_bad_search_specs_exit_2(simulated, tmp_path, args: list[str], message: str | None) -> None:
    scenario, ckpt = simulated
    if message is None:  # freezing every cell is the empty space
        args = ["--freeze", ",".join(str(c) for c in scenario.cell_ids())]
        message = "empty search space"
    run = rflscm("optimize", str(ckpt), str(scenario.root), "--out", str(tmp_path / "o"), *args)
    assert run.returncode == 2, run.stderr
    assert message in run.stderr and len(run.stderr.strip().splitlines()) == 1


def test_verify_without_truth_exits_2(tmp_path) -> None:
    root = tiny_scenario(tmp_path / "tiny", seed=2)
    ckpt = _checkpoint(load_scenario(root), tmp_path / "t.ckpt")
    run = rflscm("optimize", str(ckpt), str(root), "--verify", "--out", str(tmp_path / "o"))
    assert run.returncode == 2 and "has no truth folder" in run.stderr
    assert len(run.stderr.strip().splitlines()) == 1
