"""B10 (scale) at a tiny size: every stage runs as a process, its time and peak memory are recorded, the
growth exponent is fitted, and a failing stage skips the size's later ones."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rflscm.bench import BENCHMARKS, load_all
from rflscm.bench.b10_scale import B10Plan, growth_exponent, run_b10, run_stage
from rflscm.errors import ConfigError

TINY = B10Plan(sites=(1, 2), grids_per_site=12, scene="small", carriers="3.5e9")


def test_b10_runs_every_stage_at_two_sizes(tmp_path: Path) -> None:
    result = run_b10(TINY, tmp_path)
    rows = result["stages"]
    assert [(r["sites"], r["stage"]) for r in rows] == [
        (s, st) for s in (1, 2) for st in ("simulate", "check", "train_wnomp", "evaluate_wnomp")
    ]
    assert all(r["status"] == "ok" for r in rows), [(r["stage"], r["status"]) for r in rows]
    assert [s["cells"] for s in result["sizes"]] == [3, 6]
    assert [s["grids"] for s in result["sizes"]] == [12, 24]
    assert all(s["measurement_rows"] > 0 for s in result["sizes"])
    for r in rows:
        assert r["wall_s"] > 0 and r["peak_rss_mb"] > 100  # a Python process with torch: well above 100 MB
        assert r["command"].startswith("rflscm --threads 1 ")
    assert set(result["growth"]) == {"simulate", "check", "train_wnomp", "evaluate_wnomp"}
    assert (tmp_path / "b10" / "b10_scale.png").is_file() and result["plot"] == "b10_scale.png"
    csv_lines = (tmp_path / "b10" / "b10_scale.csv").read_text().splitlines()
    assert len(csv_lines) == 1 + len(rows) and csv_lines[0].startswith("sites,cells,stage")
    metrics = json.loads((tmp_path / "b10" / "city2" / "wnomp_eval.json").read_text())
    assert metrics  # the evaluation wrote its metrics


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
    yaml_file.write_text("sites: [5, 9]\ngrids_per_site: 6\nscene: ground\nrflscm_minutes: 2\n")
    plan = plan_of(ctx(config=str(yaml_file)))
    assert (plan.sites, plan.grids_per_site, plan.scene, plan.rflscm_minutes) == ((5, 9), 6, "ground", 2)
    plan = plan_of(ctx(config=str(yaml_file), sites=(3,), minutes=1.5))
    assert plan.sites == (3,) and plan.rflscm_minutes == 1.5 and plan.grids_per_site == 6
    yaml_file.write_text("sites: [5]\ngrid: 6\n")
    with pytest.raises(ConfigError, match="unknown B10 key"):
        plan_of(ctx(config=str(yaml_file)))
