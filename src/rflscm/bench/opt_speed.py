"""Speed of ``rflscm optimize`` on the shipped scenario once the APS are cached (issue 13 targets:
≥ 1000 single-cell candidate configurations per second on 2 CPU cores, the whole scenario in ≤ 2 min).

Candidate throughput: every cell's tilt, electrical-tilt and azimuth lines (16 + 16 + 13 candidates)
scored as the search does (batched sensing build + one product with the cached APS + KPIs), on (a) the
true APS (the bins the ray tracer fills) and (b) a dense APS on all 6552 bins (the worst case of a
field model whose every bin is non-zero), and (c) the RF-LSCM APS of B7 when ``<out>/b7_checkpoints/
rflscm_aps.pt`` exists.  Whole-scenario time: coordinate descent with 2 restarts, coverage objective.
Wall and process CPU time are both recorded: on a shared machine the wall time says how busy it was,
the CPU time (one thread with ``--threads 1``) what the work costs.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from rflscm.bench import BenchContext, register_bench
from rflscm.bench.harness import scenario_path

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.eval.cache import ScenarioAPS


@register_bench(
    "optspeed",
    "rflscm optimize speed: candidate configurations per second, whole-scenario search time",
)
def run(ctx: BenchContext) -> dict[str, Any]:
    from rflscm.data import load_scenario
    from rflscm.eval.cache import ScenarioAPS
    from rflscm.eval.oracle import OracleModel
    from rflscm.geometry import AngleGrid

    path, _ = scenario_path(ctx)
    scen = load_scenario(path)
    oracle = OracleModel.for_scenario(scen, AngleGrid(), "cpu")
    caches = {"true_aps": ScenarioAPS.render(oracle, scen), "dense_6552_bins": _dense(scen)}
    rf = Path(ctx.out_dir) / "b7_checkpoints" / "rflscm_aps.pt"
    if rf.is_file():
        caches["rflscm_b7"] = ScenarioAPS.load(rf)  # B7's own file (of its size's sub-scenario): integrity checks only
    out: dict[str, Any] = {
        "threads": torch.get_num_threads(),
        "notes": __doc__.split("\n\n")[-1],
    }
    for name, cache in caches.items():
        out[name] = _measure(scen, cache, whole=name != "dense_6552_bins")
    return out


def _dense(scen: Scenario) -> ScenarioAPS:
    from rflscm.eval.cache import ScenarioAPS
    from rflscm.geometry import AngleGrid

    grid = AngleGrid()
    gen = torch.Generator().manual_seed(0)
    cells, grids = scen.cell_ids(), scen.grid_ids()
    aps = [torch.rand(len(grids), grid.num_bins, generator=gen) * 1e-12 for _ in cells]
    known = np.ones((len(cells), len(grids)), dtype=bool)
    return ScenarioAPS(cells, grids, [np.arange(grid.num_bins) for _ in cells], aps, known, grid, "dense")


def _measure(scen: Scenario, cache: ScenarioAPS, whole: bool) -> dict[str, Any]:
    from rflscm.network.kpi import KPIConfig
    from rflscm.network.search import NetworkEvaluator, _line, coordinate_descent
    from rflscm.network.space import build_space

    space = build_space({}, scen.cells[1], scen.meta.codebooks)
    ev = NetworkEvaluator(scen, 1, cache, space, KPIConfig(), "coverage")
    count, t0, c0 = 0, time.perf_counter(), time.process_time()
    for pos in range(len(space.cells)):
        for var in (1, 2, 3):
            cands = _line(ev, pos, var)
            ev.score_cell(pos, cands)
            count += len(cands)
    elapsed, cpu = time.perf_counter() - t0, time.process_time() - c0
    out: dict[str, Any] = {
        "kept_bins_mean": float(np.mean([len(b) for b in cache.bins])),
        "candidates": count,
        "candidates_time_s": elapsed,
        "candidates_cpu_s": cpu,
        "candidates_per_s": count / elapsed,
        "candidates_per_cpu_s": count / cpu,
    }
    if whole:
        c0 = time.process_time()
        result = coordinate_descent(ev, restarts=2)
        out.update(
            whole_scenario_search_s=result.time_s,
            whole_scenario_cpu_s=time.process_time() - c0,
            whole_scenario_evaluations=result.evaluations,
            coverage_objective=[result.base_objective, result.objective],
        )
    return out
