"""B10 (scale) at a tiny size: every stage runs as a process, its time and peak memory are recorded, the
growth exponent is fitted, and a failing stage skips the size's later ones."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rflscm.bench import BENCHMARKS, load_all
from rflscm.bench.b10_scale import B10Plan, _commands, growth_exponent, project_wall, run_b10, run_stage
from rflscm.errors import ConfigError

TINY = B10Plan(sites=(1, 2), grids_per_site=12, scene="small", carriers="3.5e9", optimize_sites=1)


def test_b10_runs_every_stage_at_two_sizes(tmp_path: Path) -> None:
    result = run_b10(TINY, tmp_path)
    rows = result["stages"]
    assert [(r["sites"], r["stage"]) for r in rows] == [
        (s, st) for s in (1, 2) for st in ("simulate", "check", "train_wnomp", "evaluate_wnomp", "optimize_wnomp")
    ]
    assert all(r["status"] == "ok" for r in rows), [(r["stage"], r["status"]) for r in rows]
    assert [s["cells"] for s in result["sizes"]] == [3, 6]
    assert [s["grids"] for s in result["sizes"]] == [12, 24]
    assert all(s["measurement_rows"] > 0 for s in result["sizes"])
    for r in rows:
        assert r["wall_s"] > 0 and r["peak_rss_mb"] > 100  # a Python process with torch: well above 100 MB
        assert r["command"].startswith("rflscm --threads 1 ")
    assert set(result["growth"]) == {"simulate", "check", "train_wnomp", "evaluate_wnomp", "optimize_wnomp"}
    assert (tmp_path / "b10" / "city2" / "opt_wnomp").is_dir()  # the optimiser wrote its report
    opt = next(r for r in rows if r["sites"] == 2 and r["stage"] == "optimize_wnomp")
    assert "--cells" in opt["command"] and result["sizes"][1]["optimize_cells"] == 3  # one site's 3 cells
    proj = result["projection"]["stages"]["optimize_wnomp"]
    assert proj["from_cells"] == 6 and not proj["spread"]
    assert (tmp_path / "b10" / "b10_scale.png").is_file() and result["plot"] == "b10_scale.png"
    csv_lines = (tmp_path / "b10" / "b10_scale.csv").read_text().splitlines()
    assert len(csv_lines) == 1 + len(rows) and csv_lines[0].startswith("sites,cells,stage")
    metrics = json.loads((tmp_path / "b10" / "city2" / "wnomp_eval.json").read_text())
    assert metrics  # the evaluation wrote its metrics


@pytest.mark.slow
def test_simulate_on_two_workers_is_timed_beside_one_and_checked_file_for_file(tmp_path: Path) -> None:
    pytest.importorskip("ray")
    plan = B10Plan(sites=(2,), grids_per_site=12, scene="small", carriers="3.5e9", workers=(1, 2))
    rows = {r["stage"]: r for r in run_b10(plan, tmp_path)["stages"]}
    assert rows["simulate@2"]["status"] == "ok" and rows["simulate@2"]["same_as_first"] is True
    assert rows["simulate@2"]["wall_s"] > 0 and rows["simulate@2"]["peak_rss_mb"] > 100
    assert not (tmp_path / "b10" / "city2" / "scenario_w2").exists()  # the identical copy was removed
    assert rows["optimize_wnomp"]["status"] == "ok"  # the later stages ran on the first scenario


def test_a_failing_stage_skips_the_rest_and_a_time_limit_stops_a_stage(tmp_path: Path) -> None:
    plan = B10Plan(sites=(1,), grids_per_site=12, scene="atlantis", carriers="3.5e9")
    rows = run_b10(plan, tmp_path)["stages"]
    assert rows[0]["status"] == "failed (exit 2)"  # unknown scene: a one-line error
    assert all(r["status"].startswith("skipped") for r in rows[1:])
    slow = run_stage(["python", "-c", "import time; time.sleep(30)"], tmp_path / "slow.log", timeout_s=1.0)
    assert slow["rc"] == 124 and slow["wall_s"] < 20


def test_growth_exponent_and_plan_checks() -> None:
    assert growth_exponent([10.0, 100.0, 1000.0], [2.0, 20.0, 200.0]) == pytest.approx(1.0)
    assert growth_exponent([10.0, 100.0], [1.0, 100.0]) == pytest.approx(2.0)
    assert growth_exponent([10.0], [1.0]) is None
    with pytest.raises(ConfigError, match="--sites"):
        B10Plan(sites=())
    with pytest.raises(ConfigError, match="rflscm-minutes"):
        B10Plan(rflscm_minutes=0.0)
    load_all()
    assert "b10" in BENCHMARKS


def test_plan_from_config_yaml_and_command_line(tmp_path: Path) -> None:
    from rflscm.bench import BenchContext
    from rflscm.bench.b10_scale import FULL_SITES, QUICK_SITES, plan_of

    def ctx(**kw) -> BenchContext:
        return BenchContext(size=kw.pop("size", "quick"), seeds=1, out_dir=tmp_path, device="cpu", scenario=None, **kw)

    assert plan_of(ctx()).sites == QUICK_SITES and plan_of(ctx(size="full")).sites == FULL_SITES
    yaml_file = tmp_path / "b10.yaml"
    yaml_file.write_text(
        "sites: [5, 9]\ngrids_per_site: 6\nscene: ground\nrflscm_minutes: 2\ntile_sites: 3\nworkers: [1, 2]\n"
        "extra: {optimize_rflscm: [--restarts, 0]}\n"
    )
    plan = plan_of(ctx(config=str(yaml_file)))
    assert (plan.sites, plan.grids_per_site, plan.scene, plan.rflscm_minutes) == ((5, 9), 6, "ground", 2)
    assert (plan.tile_sites, plan.workers, plan.extra) == (3, (1, 2), {"optimize_rflscm": ("--restarts", "0")})
    plan = plan_of(ctx(config=str(yaml_file), sites=(3,), minutes=1.5))
    assert plan.sites == (3,) and plan.rflscm_minutes == 1.5 and plan.grids_per_site == 6
    yaml_file.write_text("sites: [5]\ngrid: 6\n")
    with pytest.raises(ConfigError, match="unknown B10 key"):
        plan_of(ctx(config=str(yaml_file)))
    yaml_file.write_text(f"sites: [5]\ngiven: {{5: {tmp_path}}}\n")
    with pytest.raises(ConfigError, match=r"has no scenario\.yaml"):
        plan_of(ctx(config=str(yaml_file)))
    yaml_file.write_text("sites: [5]\nextra: {optimise: [--restarts, 0]}\n")
    with pytest.raises(ConfigError, match="unknown stage"):
        plan_of(ctx(config=str(yaml_file)))


def test_rflscm_stages_run_tiled_and_once_per_worker_count(tmp_path: Path) -> None:
    plan = B10Plan(
        sites=(4,), rflscm_minutes=2.0, tile_sites=2, workers=(1, 2), extra={"optimize_rflscm": ("--restarts", "0")}
    )
    cmds = _commands(plan, 4, tmp_path)
    assert list(cmds) == [
        "simulate",
        "simulate@2",
        "check",
        "train_wnomp",
        "evaluate_wnomp",
        "optimize_wnomp",
        "train_rflscm",
        "predict_rflscm",
        "predict_rflscm@2",
        "evaluate_rflscm",
        "evaluate_rflscm@2",
        "optimize_rflscm",
        "optimize_rflscm@2",
    ]
    train = cmds["train_rflscm"]
    assert train[train.index("--tile-sites") + 1] == "2" and train[train.index("--workers") + 1] == "2"
    assert "--workers" not in cmds["evaluate_rflscm"] and cmds["evaluate_rflscm@2"][-2:] == ["--workers", "2"]
    assert cmds["optimize_rflscm"][-2:] == ["--restarts", "0"] and cmds["optimize_rflscm@2"][-2:] == ["--restarts", "0"]
    outs = {c[c.index("--out") + 1] for k, c in cmds.items() if k.startswith("optimize")}
    assert len(outs) == 3  # serial and parallel runs never write over each other
    sims = [cmds[k][cmds[k].index("--out") + 1] for k in ("simulate", "simulate@2")]
    assert sims == [str(tmp_path / "scenario"), str(tmp_path / "scenario_w2")]  # later stages read the first
    assert cmds["simulate@2"][-2:] == ["--workers", "2"] and cmds["check"][-1] == sims[0]
    given = B10Plan(sites=(4,), rflscm_minutes=2.0, given={4: "/data/city4"}, predict=False)
    cmds = _commands(given, 4, tmp_path)
    assert (
        cmds["check"][-1] == "/data/city4"
        and cmds["evaluate_rflscm"][cmds["evaluate_rflscm"].index("evaluate") + 2] == "/data/city4"
    )
    assert not any(k.startswith("predict") for k in cmds)
    with pytest.raises(ConfigError, match="tile_sites"):
        B10Plan(tile_sites=0)
    with pytest.raises(ConfigError, match="workers"):
        B10Plan(workers=(0,))


def test_projection_is_linear_in_cells_and_divides_only_the_stages_that_spread() -> None:
    rows = [
        {"stage": "simulate", "status": "ok", "cells": 100, "wall_s": 50.0},
        {"stage": "simulate", "status": "ok", "cells": 1000, "wall_s": 400.0},
        {"stage": "check", "status": "ok", "cells": 1000, "wall_s": 80.0},
        {"stage": "evaluate_rflscm", "status": "ok", "cells": 1000, "wall_s": 300.0},
        {"stage": "train_rflscm", "status": "failed (exit 1)", "cells": 1000, "wall_s": 1.0},
    ]
    proj = project_wall(rows, 10_000, (1, 8))
    assert proj["stages"]["simulate"]["wall_s"] == {"1": pytest.approx(4000.0), "8": pytest.approx(500.0)}
    assert proj["stages"]["check"]["wall_s"] == {"1": pytest.approx(800.0), "8": pytest.approx(800.0)}
    assert proj["stages"]["evaluate_rflscm"]["wall_s"] == {"1": pytest.approx(3000.0), "8": pytest.approx(375.0)}
    assert "train_rflscm" not in proj["stages"]  # a failed stage projects nothing
