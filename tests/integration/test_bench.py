"""The paper benchmarks B1–B6 end to end at the ``tiny`` size on a tiny procedural scenario.

These check the plumbing — every model trains under its protocol, the result has its documented
keys, is JSON-able and the plots are written — not the numbers (a handful of steps learns nothing).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from rflscm.bench import BENCHMARKS, BenchContext, load_all
from rflscm.bench.harness import bench_size, load_bench_data, restrict_round1, sub_scenario, tiny_size

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_thread")]


@pytest.fixture(scope="module")
def scenario_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario

    size = tiny_size()
    cfg = SimulationConfig(
        name="bench-tiny",
        num_sites=2,
        max_grids=40,
        seed=3,
        site_radius_m=70.0,
        point_cloud_points_per_m2=0.05,
        angle_grid=size.grid(),
    )
    out = tmp_path_factory.mktemp("bench") / "scen"
    build_scenario(ProceduralCity(seed=2, size_m=180.0, num_buildings=8), cfg, out, progress=False)
    return out


def ctx_for(tmp_path: Path, scenario_dir: Path, seeds: int = 1) -> BenchContext:
    return BenchContext(size="tiny", seeds=seeds, out_dir=tmp_path, device="cpu", scenario=str(scenario_dir))


def check_common(result: dict, tmp_path: Path) -> None:
    json.dumps(result)  # JSON-able as the CLI writes it
    assert {"size", "scenario", "seeds", "notes", "plots"} <= set(result)
    assert result["size"]["name"] == "tiny" and result["scenario"]["oracle"] is True
    for name in result["plots"]:
        png = tmp_path / name
        assert png.is_file() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_all_benchmarks_registered_and_sizes_documented() -> None:
    load_all()
    assert {"b1", "b2", "b3", "b4", "b5", "b6"} <= set(BENCHMARKS)
    quick = bench_size("quick")
    assert quick.max_sites == 1 and quick.overrides["rflscm"]["train"]["steps"] > 0
    assert bench_size("full").max_sites is None and bench_size("full").preset == "full"


def test_sub_scenario_is_deterministic_and_keeps_whole_sites(scenario_dir: Path) -> None:
    from rflscm.data import load_scenario

    full = load_scenario(scenario_dir)
    a, info = sub_scenario(full, tiny_size())
    b, _ = sub_scenario(full, tiny_size())
    assert a.measurements.equals(b.measurements) and info["grids"] == 24
    site = full.cells[1].set_index("cell_id").loc[info["cells"], "site_id"].unique()
    assert len(site) == 1 and len(info["cells"]) == int((full.cells[1]["site_id"] == site[0]).sum())
    assert set(a.measurements["cell_id"]) == set(info["cells"]) and set(a.measurements["round"]) == {1, 2}
    assert len(a.point_cloud.xyz) < len(full.point_cloud.xyz)


def test_bench_oracle_is_fitted_on_the_sub_scenario(tmp_path: Path, scenario_dir: Path) -> None:
    from rflscm.sim.truth import load_true_aps

    size = tiny_size()
    data = load_bench_data(ctx_for(tmp_path, scenario_dir), size)
    sub = data.scenario
    assert len(sub.grid_ids()) < len(data.full.grid_ids())
    assert data.oracle.fingerprint == sub.fingerprint()  # like every other model, not the full scenario's
    c, g = np.repeat(sub.cell_ids(), len(sub.grid_ids())), np.tile(sub.grid_ids(), len(sub.cell_ids()))
    torch.testing.assert_close(data.oracle.aps(c, g), load_true_aps(data.full, size.grid()).aps(c, g), rtol=0, atol=0)


def test_restrict_round1_keeps_round2(tmp_path: Path, scenario_dir: Path) -> None:
    data = load_bench_data(ctx_for(tmp_path, scenario_dir), tiny_size())
    restricted, grids = restrict_round1(data, 0.25)
    m = restricted.scenario.measurements
    assert set(m.loc[m["round"] == 1, "grid_id"]) == set(grids.tolist())
    assert (m["round"] == 2).sum() == (data.scenario.measurements["round"] == 2).sum()


def test_b1_adjust(tmp_path: Path, scenario_dir: Path) -> None:
    from rflscm.bench.b01_adjust import run_b1

    res = run_b1(ctx_for(tmp_path, scenario_dir), tiny_size())
    check_common(res, tmp_path)
    assert set(res["models"]) == {"rflscm", "nerf2", "wnomp"}
    for entry in res["models"].values():
        assert set(entry["mae_db"]) == {"ssb", "csi"} and set(entry["mae_db"]["ssb"]) == {"all", "changed"}
        assert entry["mae_db"]["ssb"]["all"] is not None and entry["train_time_s"] > 0
        # on Linux the probe samples the RSS: a process holding torch and a scenario is ≥ 50 MB, and the
        # peak can never lie below its own increase over the start
        assert entry["memory_kind"] == "cpu_rss" and entry["peak_memory_mb"] > 50
        assert entry["peak_memory_mb"] >= entry["memory_increase_mb"] >= 0
    for name in ("rflscm", "nerf2"):
        tp = res["models"][name]["throughput"]
        assert tp["ray_samples_per_s"] > 0 and res["models"][name]["parameters"] > 0
    assert res["oracle"]["mae_db"]["csi"]["all"] is not None and res["changed_cells"]
    # over the pairs with round-1 reports every model scores the same pairs: WNOMP's equal its all-pairs MAE (it
    # answers nothing else)
    wnomp = res["models"]["wnomp"]
    assert wnomp["seen_mae_db"] == wnomp["mae_db"] and res["models"]["rflscm"]["seen_mae_db"]["ssb"]["all"] is not None
    assert set(res["seen"]) == {"oracle", "trivial"} and res["seen"]["oracle"]["ssb"]["all"] is not None
    # chosen on held-aside round-1 beams of the adjust protocol's training data, as the demo chooses them
    from rflscm.bench.harness import build_model, selected_wnomp
    from rflscm.eval import AdjustProtocol

    data = load_bench_data(ctx_for(tmp_path, scenario_dir), tiny_size())
    training = AdjustProtocol().training_scenario(data.scenario)
    again = selected_wnomp(build_model(data, "wnomp", None, 0, "cpu"), training, 0, "cpu")
    assert res["models"]["wnomp"]["settings"] == again.run_info["wnomp_selection"]["chosen"]


def test_bench_wnomp_settings_never_see_round2_or_held_out_grids(tmp_path: Path, scenario_dir: Path) -> None:
    from rflscm.bench.harness import selected_wnomp
    from rflscm.eval import UnseenProtocol
    from rflscm.models.wnomp import WNOMPConfig, WNOMPModel

    data = load_bench_data(ctx_for(tmp_path, scenario_dir), tiny_size())
    protocol = UnseenProtocol(fraction=0.25, seed=0)
    base = WNOMPModel(WNOMPConfig(k_max=4), tiny_size().grid())
    m = data.scenario.measurements
    scrambled = m.copy()  # round 2 and the held-out grids replaced by garbage
    hidden = (m["round"] == 2).to_numpy() | m["grid_id"].isin(protocol.held_out(data.scenario)).to_numpy()
    scrambled.loc[hidden & m["rsrp_dbm"].notna().to_numpy(), "rsrp_dbm"] = -60.0
    choices = []
    for table in (m, scrambled):
        scenario = data.scenario.with_measurements(table, validate=False)
        model = selected_wnomp(base, protocol.training_scenario(scenario), seed=0, device="cpu")
        choices.append(model.run_info["wnomp_selection"])
    assert choices[0]["chosen"] == choices[1]["chosen"] and choices[0]["candidates"] == choices[1]["candidates"]
    assert len(choices[0]["candidates"]) == 12 and choices[0]["candidates"][0]["beams"] > 0
    chosen = choices[0]["chosen"]
    best = min(choices[0]["candidates"], key=lambda row: row["mae_db"])
    assert (chosen["k_max"], chosen["weighting"]) == (best["k_max"], best["weighting"])


def test_b2_convergence_two_seeds(tmp_path: Path, scenario_dir: Path) -> None:
    from rflscm.bench.b02_convergence import VARIANTS, run_b2

    res = run_b2(ctx_for(tmp_path, scenario_dir, seeds=2), tiny_size())
    check_common(res, tmp_path)
    assert res["seeds"] == [0, 1] and set(res["variants"]) == set(VARIANTS)
    for entry in res["variants"].values():
        assert len(entry["raw_curves"]) == 2 and entry["final_val_mae_db"]["n"] == 2
        curve = entry["curve"]
        assert len(curve["time_s"]) == len(curve["mae_mean_db"]) == len(curve["mae_std_db"])
        assert np.all(np.diff(curve["time_s"]) >= 0)
    assert res["target_mae_db"] is not None and set(res["hitam_speedup"]) == {"rflscm", "nerf2"}
    assert max(e["reached"] for e in res["variants"].values()) >= 1  # the best mean curve lies below the target
    for entry in res["variants"].values():  # a seed that reached the target did so within its training time
        target = res["target_mae_db"]
        assert entry["reached"] == sum(
            any(np.isfinite(m) and m <= target for _, _, m in c) for c in entry["raw_curves"]
        )
        if entry["reached"]:
            assert 0 <= entry["time_to_target_s"]["mean"] <= max(c[-1][0] for c in entry["raw_curves"]) + 1e-9


def test_b3_multifreq(tmp_path: Path, scenario_dir: Path) -> None:
    from rflscm.bench.b03_multifreq import run_b3

    res = run_b3(ctx_for(tmp_path, scenario_dir), tiny_size())
    check_common(res, tmp_path)
    assert res["percents"] == [5.0, 30.0] and set(res["arms"]) == {"with_other_band", "without_other_band"}
    for arm in res["arms"].values():
        assert set(arm) == {"p5", "p30"} and arm["p5"]["train_grids"] <= arm["p30"]["train_grids"]
        assert arm["p30"]["mae_db"]["ssb"] is not None and arm["p30"]["trivial_mae_db"]["csi"] is not None
    assert set(res["gain_db"]["p5"]) == {"ssb", "csi"} and res["carrier_hz"] == pytest.approx(2.1e9)


def test_b4_point_cloud(tmp_path: Path, scenario_dir: Path) -> None:
    from rflscm.bench.b04_point_cloud import run_b4

    res = run_b4(ctx_for(tmp_path, scenario_dir, seeds=2), tiny_size())
    check_common(res, tmp_path)
    assert set(res["variants"]) == {"prior_on", "prior_off"} and len(res["plots"]) == 2
    assert res["train_grids"] >= 1 and set(res["prior_gain_db"]) == {"ssb", "csi"}
    # each seed draws its own training grids, and the gain is the mean of the paired per-seed gains
    draws = list(res["train_grid_ids"].values())
    assert len(draws) == 2 and draws[0] != draws[1]
    per_seed = res["prior_gain_per_seed_db"]
    assert res["prior_gain_db"]["ssb"] == pytest.approx((per_seed[0]["ssb"] + per_seed[1]["ssb"]) / 2)
    assert res["variants"]["prior_on"]["mae_db"]["csi"]["all"] is not None


def test_b5_alpha_p(tmp_path: Path, scenario_dir: Path) -> None:
    from rflscm.bench.b05_alpha_p import run_b5

    res = run_b5(ctx_for(tmp_path, scenario_dir), tiny_size())
    check_common(res, tmp_path)
    assert set(res["sweep"]) == {"0", "0.5"}
    # α_P reaches the loss: the two runs differ (same seed, same data)
    assert res["sweep"]["0"]["mae_db"]["ssb"]["all"] != res["sweep"]["0.5"]["mae_db"]["ssb"]["all"]
    # the tiny scenario has beams missing in round 2, so the share above the bound is defined
    assert res["sweep"]["0"]["missing_above_bound"] is not None
    # the truth scores every beam above r_th: defined for the sweep, the oracle and trivial
    assert res["sweep"]["0.5"]["truth_mae_db"]["csi"]["all"] is not None
    assert res["oracle"]["truth_mae_db"]["ssb"]["all"] < res["trivial"]["truth_mae_db"]["ssb"]["all"]
    truth = {float(a): e["truth_mae_db"]["ssb"]["all"] for a, e in res["sweep"].items()}
    assert res["best_alpha_truth"]["ssb"] == min(truth, key=lambda a: (truth[a], a))


def test_b6_unseen(tmp_path: Path, scenario_dir: Path) -> None:
    from rflscm.bench.b06_unseen import run_b6

    res = run_b6(ctx_for(tmp_path, scenario_dir), tiny_size())
    check_common(res, tmp_path)
    assert res["holdout_grids"] >= 1
    models = res["models"]
    assert models["wnomp"]["unseen_mae_db"]["ssb"] is None  # no notion of unseen grids
    assert models["wnomp"]["aps_seen"]["nmse_db"] is not None and models["wnomp"]["aps_seen"]["pairs"] > 0
    for name in ("rflscm", "nerf2"):
        assert models[name]["unseen_mae_db"]["ssb"] is not None
        assert models[name]["aps_unseen"]["angle_error_deg"] is not None


def test_b9_time_to_target_tiny(tmp_path: Path, scenario_dir: Path) -> None:
    """Old (a copy of today's src given as --baseline) and new model in their own processes, WNOMP's level."""
    import shutil

    import rflscm
    from rflscm.bench.b09_time_to_target import run_b9
    from rflscm.data import BEAM_TYPES

    baseline = tmp_path / "old"
    shutil.copytree(
        Path(rflscm.__file__).parent, baseline / "src" / "rflscm", ignore=shutil.ignore_patterns("__pycache__")
    )
    ctx = BenchContext(
        size="tiny", seeds=1, out_dir=tmp_path, device="cpu", scenario=str(scenario_dir), baseline=str(baseline)
    )
    res = run_b9(ctx, "tiny")
    json.dumps(res)
    assert res["settings"]["threads"] == 1 and res["settings"]["baseline"] == str((baseline / "src").resolve())
    assert list(res["regimes"]) == ["given"] and res["plots"] == ["b9_given.png"]
    assert (tmp_path / "b9_given.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    entry = res["regimes"]["given"]
    for who in ("old", "new"):
        run = entry[who]
        assert run["threads"] == 1 and run["steps_done"] == 30 and run["stopped_by"] == "schedule"
        assert len(run["rows"]) >= 2 and run["rows"][-1]["step"] == 30
        times = [r["train_s"] for r in run["rows"]]
        assert all(np.isfinite(times)) and times[0] > 0
        # a row's time includes its own finish_training (level correction, anchors, ...), not earlier rows'
        base = [r["train_s"] - r["finish_s"] for r in run["rows"]]
        assert base == sorted(base) and all(r["finish_s"] > 0 for r in run["rows"][:-1])
        for row in run["rows"]:
            assert np.isfinite(row["cpu_s"]) and row["eval_s"] > 0
            for bt in BEAM_TYPES:
                assert all(np.isfinite(row["mae_db"][bt][k]) for k in ("all", "changed"))
    # the new model's fallback answers with the settings of the WNOMP it is compared with; the old code has no such key
    assert entry["new"]["overrides"]["corrections"]["wnomp_fallback"] == entry["wnomp"]["config"]
    assert "corrections" not in entry["old"]["overrides"]
    old_src = Path(entry["old"]["rflscm_file"]).parents[1]
    assert old_src == (baseline / "src").resolve()  # the worker imported the baseline's copy
    assert Path(entry["new"]["rflscm_file"]).parents[1] != old_src
    for bt in BEAM_TYPES:
        level = entry["wnomp"]["mae_db"][bt]["changed"]
        assert level is not None and np.isfinite(level)
        cmp = entry["comparison"][bt]
        assert cmp["wnomp_mae_db"] == level and cmp["basis"] in ("wnomp", "old_best")
        assert cmp["old_best_mae_db"] is not None and cmp["old_time_to_best_s"] > 0


def test_b8_realism_tiny(tmp_path: Path, scenario_dir: Path) -> None:
    """Two steps of the sweep: every model and floor scored per step, the re-measured folders reused."""
    from rflscm.bench.b08_realism import run_b8
    from rflscm.data import load_scenario

    ctx = ctx_for(tmp_path, scenario_dir)
    res = run_b8(ctx, tiny_size(), steps=("ideal", "reporting"))
    json.dumps(res)
    assert list(res["steps"]) == ["ideal", "reporting"] and res["plots"] == ["b8_realism.png"]
    assert (tmp_path / "b8_realism.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    for step, entry in res["steps"].items():
        for label in ("wnomp", "rflscm", "nerf2", "model_floor", "noise_floor", "trivial"):
            assert entry[label]["mae_db"]["ssb"]["all"] is not None, (step, label)
        assert entry["rflscm"]["steps"] == tiny_size().overrides["rflscm"]["train"]["steps"]
        assert len(entry["wnomp_selection"]) == 12  # the candidate with the lowest held-aside MAE is chosen
        best = min(entry["wnomp_selection"], key=lambda r: r["mae_db"] if np.isfinite(r["mae_db"]) else np.inf)
        chosen = entry["wnomp_settings"]
        assert (chosen["k_max"], chosen["weighting"]) == (best["k_max"], best["weighting"]), step
    ideal, field = (load_scenario(tmp_path / "b8" / s) for s in ("ideal", "reporting"))
    assert ideal.meta.reporting != field.meta.reporting  # each step re-measured in its own regime
    reported = {s: e["reported_beams_round1"]["csi"] for s, e in res["steps"].items()}
    assert reported["reporting"] < reported["ideal"]  # serving-cell top-4 CSI-RS reports fewer beams
    table = (tmp_path / "b8.md").read_text().splitlines()
    assert len(table) == 4 and table[2].startswith("| ideal |")
    from rflscm.bench.b08_realism import measured

    stamp = (tmp_path / "b8" / "ideal" / "scenario.yaml").stat().st_mtime_ns
    assert measured(scenario_dir, "ideal", tmp_path / "b8" / "ideal").name == "ideal"  # same measurement: reused
    assert (tmp_path / "b8" / "ideal" / "scenario.yaml").stat().st_mtime_ns == stamp
    measured(scenario_dir, "reporting", tmp_path / "b8" / "ideal")  # another regime in that folder: re-measured
    assert load_scenario(tmp_path / "b8" / "ideal").meta.reporting == field.meta.reporting


def test_b9_without_a_baseline_folder_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys) -> None:
    """``rflscm bench b9`` needs the old model's code as a folder (no git): one line, exit 2, nothing run."""
    from check_helpers import assert_one_line_error, run_cli

    out = tmp_path / "b9"
    assert_one_line_error(*run_cli(["bench", "b9", "--out", str(out)], monkeypatch, capsys), ["--baseline PATH"])
    code, stdout, err = run_cli(["bench", "b9", "--out", str(out), "--baseline", str(tmp_path)], monkeypatch, capsys)
    assert_one_line_error(code, stdout, err, [str(tmp_path), "holds no src/rflscm"])
    assert not (out / "b9_runs").exists() and not (out / "b9.json").exists()


def test_import_bench_trains_both_models_on_source_and_imported(tmp_path: Path, scenario_dir: Path) -> None:
    from rflscm.bench.import_roundtrip import run_import

    load_all()
    assert "import" in BENCHMARKS
    result = run_import(ctx_for(tmp_path, scenario_dir), tiny_size())
    json.dumps(result)
    assert (tmp_path / "import_raw" / "import.yaml").is_file() and (tmp_path / "import_scenario").is_dir()
    made = result["import"]
    assert made["import"]["point_cloud_points"] == made["raw"]["cloud_points"] > 0
    assert made["import"]["samples_read"] == made["raw"]["samples"]
    arms = result["arms"]
    assert arms["imported"]["point_cloud_points"] > 0 and arms["imported"]["reported_beams"]["2"] > 0
    assert arms["source"]["sites"] == arms["imported"]["sites"]
    for model in ("wnomp", "rflscm"):
        entry = result["models"][model]
        for bt in ("ssb", "csi"):
            src, imp = entry["source"]["mae_db"][bt]["all"], entry["imported"]["mae_db"][bt]["all"]
            assert src is not None and imp is not None
            assert entry["imported_minus_source_db"][bt]["all"] == pytest.approx(imp - src)
    assert len(result["table"]) == 2 + 3 * 2 and result["table"][2].startswith("| wnomp | source |")
    again = run_import(ctx_for(tmp_path, scenario_dir), tiny_size(), models=("wnomp",))  # replaces its own output
    assert again["models"]["wnomp"]["source"]["mae_db"] == result["models"]["wnomp"]["source"]["mae_db"]
