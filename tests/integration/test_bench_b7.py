"""B7 (network optimisation, verified on truth) end to end at the ``tiny`` size on a tiny procedural scenario:
plumbing and documented keys, not the numbers."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from rflscm.bench import BENCHMARKS, BenchContext, load_all
from rflscm.bench.harness import BenchData, tiny_size

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("one_thread")]


@pytest.fixture(scope="module")
def scenario(tmp_path_factory: pytest.TempPathFactory):
    from rflscm.data import load_scenario
    from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario

    cfg = SimulationConfig(
        name="b7-tiny",
        num_sites=2,
        max_grids=30,
        seed=3,
        site_radius_m=70.0,
        point_cloud_points_per_m2=0.05,
        angle_grid=tiny_size().grid(),
    )
    out = tmp_path_factory.mktemp("b7") / "scen"
    build_scenario(ProceduralCity(seed=2, size_m=180.0, num_buildings=8), cfg, out, progress=False)
    return load_scenario(out)


def test_b7_reports_true_and_predicted_gain_per_model(scenario, tmp_path: Path) -> None:
    from rflscm.bench.b07_optimize import run_b7

    load_all()
    assert {"b7", "optspeed"} <= set(BENCHMARKS)
    ctx = BenchContext(
        size="tiny",
        seeds=1,
        out_dir=tmp_path,
        device="cpu",
        scenario=str(scenario.root),
    )
    data = BenchData(scenario, scenario, None, tiny_size(), {"name": "b7-tiny"})
    result = run_b7(ctx, data, ("rflscm", "wnomp"), restarts=0)
    json.dumps(result)
    assert set(result["models"]) == {"oracle", "rflscm", "wnomp"}
    for entry in result["models"].values():
        assert {
            "predicted_gain",
            "true_gain",
            "true_before",
            "search_time_s",
            "aps_time_s",
        } <= set(entry)
        assert entry["predicted_gain"]["coverage"] >= -1e-12  # the search never makes its own objective worse
    assert result["models"]["wnomp"]["kpi_pairs"] == "measured round-1 pairs only"
    assert "oracle" in result["winner"] and result["winner"].split(":")[0] in (
        "rflscm",
        "wnomp",
    )
    assert (tmp_path / "b7_checkpoints" / "rflscm.ckpt").is_file()  # reused by the next run
    assert set(result["optimisers_on_oracle"]) == {
        "coordinate_descent",
        "scipy_differential_evolution",
    }
