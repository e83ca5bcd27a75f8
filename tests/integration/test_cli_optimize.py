"""`rflscm optimize` end to end: new round, report, truth check, `check` round trip, `predict --kpi` match,
and one clear line + exit 2 for bad search specs."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
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
    return subprocess.run(
        [sys.executable, "-m", "rflscm.cli", "--threads", "1", *args], capture_output=True, text=True, timeout=600
    )


def summary_changes(out: Path) -> list[dict]:
    return pd.read_csv(out / "changes.csv").to_dict("records")


def _checkpoint(scenario, path: Path) -> Path:
    model = MODEL_REGISTRY["wnomp"].build(None, GRID, "cpu")
    fit_with_protocol(model, scenario, None, progress=False)
    return model.save(path)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("cli_opt") / "sc"
    config = SimulationConfig(
        num_sites=2, max_grids=40, seed=5, site_radius_m=120.0, angle_grid=GRID, point_cloud_points_per_m2=0.05
    )
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
    run = rflscm(
        "optimize",
        str(ckpt),
        str(scenario.root),
        "--out",
        str(out),
        "--tilt-range",
        "0:10:2",
        "--azimuth-range",
        "-10:10:5",
        "--max-changed",
        "3",
        "--restarts",
        "1",
        "--device",
        "cpu",
    )
    assert run.returncode == 0, run.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["kpi_pairs"] == "measured round-1 pairs only"  # WNOMP
    assert "measured round-1 pairs only" in " ".join(run.stderr.split())
    assert summary["changed_cells"] <= 3
    assert summary["search"]["objective_after"] >= summary["search"]["objective_before"]
    assert set(summary["truth"]) >= {"before", "after", "note"} and "noiseless" in summary["truth"]["note"]
    # predicted and true on the same pairs; the truth on every pair beside them for scale
    assert "same pairs" in summary["truth"]["note"] and "every (cell, grid) pair" in summary["truth_all_pairs"]["note"]
    mask = np.zeros((len(scenario.cell_ids()), len(scenario.grid_ids())), bool)
    m1 = scenario.measurements[scenario.measurements["round"] == 1]
    mask[np.searchsorted(scenario.cell_ids(), m1["cell_id"]), np.searchsorted(scenario.grid_ids(), m1["grid_id"])] = 1
    assert summary["kpi_pair_count"] == mask.sum()
    assert "held_out" not in summary and summary["verdict"]["basis"] == "true"  # with truth, no grid is held out
    report = (out / "report.md").read_text()
    assert "| coverage ratio (%) |" in report and "true gain" in report and (out / "maps_3.5GHz.png").is_file()
    assert "cover the same" in report and ("color:red" in report) == summary["verdict"]["flagged"]
    # no change beyond the documented limits
    for row in summary_changes(out):
        assert abs(row["mech_tilt_deg_after"] - row["mech_tilt_deg_before"]) <= 4
        assert abs(row["elec_tilt_deg_after"] - row["elec_tilt_deg_before"]) <= 4
        d_az = abs(row["azimuth_deg_after"] - row["azimuth_deg_before"]) % 360
        assert min(d_az, 360 - d_az) <= 10 and 0 <= row["mech_tilt_deg_after"] <= 10
    assert str(scenario.root) not in (out / "scenario" / "scenario.yaml").read_text()  # relative paths
    rnd = summary["round"]["number"]
    assert rnd == 3
    check = rflscm("check", str(out / "scenario"))
    assert check.returncode == 0, check.stderr
    again = load_scenario(out / "scenario")
    assert sorted(again.cells) == [1, 2, 3] and again.fingerprint() == scenario.fingerprint()
    pred = rflscm(
        "predict",
        str(ckpt),
        str(out / "scenario"),
        "--round",
        str(rnd),
        "--pairs",
        "measured",
        "--out",
        str(tmp_path / "p.parquet"),
        "--kpi-json",
        str(tmp_path / "k.json"),
        "--device",
        "cpu",
    )
    assert pred.returncode == 0, pred.stderr
    kpis = json.loads((tmp_path / "k.json").read_text())
    for key in ("coverage", "mean_sinr_db", "overlap", "mean_rsrp_dbm", "p5_sinr_db"):
        assert kpis[key] == pytest.approx(summary["predicted"]["after"][key], abs=1e-4), key


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--tilt-range", "10:2"], "range reversed"),
        (["--tilt-range", "0:40"], "--tilt-range 0:40: the mechanical tilt must stay within the physical limits"),
        (["--azimuth-range", "-90:90:10"], "physical limits -60…60 degrees"),
        (["--freeze", "424242"], "unknown cell 424242"),
        (["--cells", "424242"], "--cells 424242: no such cell(s) 424242"),
        (["--cells", "a,b"], "--cells takes comma-separated cell ids"),
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


def test_aps_cache_is_written_reused_and_refused_when_foreign_or_hostile(simulated, tmp_path) -> None:
    import builtins

    import torch

    scenario, ckpt = simulated
    cache = tmp_path / "aps.pt"
    small = [
        "--tilt-range",
        "0:4:2",
        "--elec-tilt-range",
        "0:0",
        "--azimuth-range",
        "0:0",
        "--restarts",
        "0",
        "--no-verify",
        "--device",
        "cpu",
        "--aps-cache",
        str(cache),
    ]
    first = rflscm("optimize", str(ckpt), str(scenario.root), "--out", str(tmp_path / "o1"), *small)
    assert first.returncode == 0, first.stderr
    written = cache.stat().st_mtime_ns
    second = rflscm("optimize", str(ckpt), str(scenario.root), "--out", str(tmp_path / "o2"), *small)
    assert second.returncode == 0, second.stderr
    assert cache.stat().st_mtime_ns == written  # read back, not rendered again
    s1, s2 = (json.loads((tmp_path / o / "summary.json").read_text()) for o in ("o1", "o2"))
    assert s1["predicted"] == s2["predicted"]

    retrained = MODEL_REGISTRY["wnomp"].build({"k_max": 2}, GRID, "cpu")  # same model name, other content
    fit_with_protocol(retrained, scenario, None, progress=False)
    other = retrained.save(tmp_path / "other.ckpt")
    run = rflscm("optimize", str(other), str(scenario.root), "--out", str(tmp_path / "o3"), *small)
    assert run.returncode == 2 and "written for another checkpoint" in run.stderr, run.stderr
    assert len(run.stderr.strip().splitlines()) == 1 and cache.stat().st_mtime_ns == written

    class Payload:
        def __reduce__(self):
            return (builtins.open, (str(tmp_path / "pwned"), "w"))

    torch.save({"format": "rflscm-aps-cache/1", "payload": Payload()}, tmp_path / "evil.pt")
    evil = [*small[:-1], str(tmp_path / "evil.pt")]
    run = rflscm("optimize", str(ckpt), str(scenario.root), "--out", str(tmp_path / "o4"), *evil)
    assert run.returncode == 2 and "refused" in run.stderr and len(run.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "pwned").exists()


def test_a_wnomp_recommendation_with_a_negative_true_gain_is_flagged(simulated, tmp_path, monkeypatch) -> None:
    """Force the search onto the single-cell change that hurts the true mean SS-SINR most (found on the truth itself) and
    check that the result, the report and the CLI's verdict flag it."""
    import rflscm.network.optimize as opt
    from rflscm.eval.cache import ScenarioAPS
    from rflscm.models import load_model
    from rflscm.network.kpi import KPIConfig, network_kpis
    from rflscm.network.report import write_report
    from rflscm.network.search import SearchResult
    from rflscm.network.space import VARIABLES, build_space, cells_table
    from rflscm.network.verify import TruthVerifier

    scenario, ckpt = simulated
    model = load_model(ckpt, scenario, device="cpu")
    cache = ScenarioAPS.render(model, scenario)
    assert not cache.known.all()  # WNOMP: measured round-1 pairs only
    kpi = KPIConfig()
    space = build_space({}, scenario.cells[1], scenario.meta.codebooks)
    base = [c.current for c in space.cells]
    truth = TruthVerifier(scenario)
    freqs = scenario.cells[1]["freq_hz"].to_numpy()

    def true_sinr(config):
        power = truth.best_power(cells_table(scenario.cells[1], space, config))
        return network_kpis(power, freqs, kpi, cache.known)["mean_sinr_db"]

    worst, worst_gain = None, 0.0
    before = true_sinr(base)
    for pos in space.free_cells():
        opts = space.cells[pos]
        for var in ("mech_tilt_deg", "azimuth_deg"):
            k = VARIABLES.index(var)
            for i in (0, opts.sizes()[k] - 1):
                config = list(base)
                config[pos] = (*opts.current[:k], i, *opts.current[k + 1 :])
                config = space.tie(config)
                gain = true_sinr(config) - before
                if gain < worst_gain:
                    worst, worst_gain = config, gain
    assert worst is not None, "no single-cell change lowers the true mean SS-SINR in this scenario"

    def forced(ev, **_):
        base_obj = ev.score()
        ev.set_config(worst)
        return SearchResult(worst, ev.score(), base_obj, ev.evaluations, 0.0, "forced")

    monkeypatch.setattr(opt, "coordinate_descent", forced)
    result = opt.run_optimize(scenario, cache, space, objective="sinr", kpi=kpi, verify=True)
    summary = result.summary()
    assert summary["true_gain"]["mean_sinr_db"] == pytest.approx(worst_gain, abs=1e-9)
    assert summary["verdict"]["flagged"] and summary["verdict"]["basis"] == "true"
    report = write_report(result, scenario, tmp_path / "o", kpi, 3, tmp_path / "o" / "scenario").read_text()
    assert "color:red" in report and "do not apply: the true mean SS-SINR gain is" in report


def test_cells_frees_a_cluster_renders_where_it_reaches_and_a_cache_of_another_cluster_is_refused(
    simulated, tmp_path
) -> None:
    scenario, ckpt = simulated
    cache = tmp_path / "aps.pt"
    small = ["--tilt-range", "0:4:2", "--elec-tilt-range", "0:0", "--azimuth-range", "0:0", "--restarts", "0"]
    small += ["--no-verify", "--device", "cpu", "--aps-cache", str(cache)]
    m = scenario.measurements
    r1 = m[(m["round"] == 1).to_numpy()]
    heard = r1.groupby("cell_id")["grid_id"].nunique().sort_values()
    cell = int(heard.index[0])  # the cell heard at the fewest grids: its area is a part of the network
    run = rflscm("optimize", str(ckpt), str(scenario.root), "--out", str(tmp_path / "o1"), "--cells", str(cell), *small)
    assert run.returncode == 0, run.stderr
    summary = json.loads((tmp_path / "o1" / "summary.json").read_text())
    changed = {int(c) for c in pd.read_csv(tmp_path / "o1" / "changes.csv")["cell_id"]}
    assert changed <= {cell}  # every other cell frozen
    area = set(r1.loc[r1["cell_id"] == cell, "grid_id"])
    in_area = r1[r1["grid_id"].isin(area)].drop_duplicates(["cell_id", "grid_id"])
    assert summary["kpi_pair_count"] == len(in_area) < len(r1.drop_duplicates(["cell_id", "grid_id"]))
    assert f"rendering the APS of {len(in_area):,} (cell, grid) pairs" in " ".join(run.stderr.split())  # said first
    run = rflscm("optimize", str(ckpt), str(scenario.root), "--out", str(tmp_path / "o2"), *small)
    assert run.returncode == 2 and "rendered for other grids" in run.stderr, run.stderr
    assert len(run.stderr.strip().splitlines()) == 1
