"""B7 — network optimisation on the learned model, verified on ray-traced truth (issue 13).

Each model (RF-LSCM, NeRF²-LSCM, WNOMP, and the oracle = true APS, the upper bound) renders the APS of
the whole scenario once; coordinate descent with restarts then searches mechanical/electrical tilt
(0…15° in 1° steps), azimuth (±30° in 5° steps) and SSB codebook of every cell for the ``coverage``
objective (best-server SSB RSRP ≥ −105 dBm).  Reported per model: the predicted gain (on its own APS;
WNOMP: measured pairs only), the TRUE gain of its recommendation (noiseless RSRP from the traced paths,
every (cell, grid) pair, the simulator's formula), the share of the oracle's true gain, and the time
(APS rendering, search, truth check).  The oracle is also searched by scipy's differential evolution
for the time coordinate descent took, to compare the optimisers per evaluation.

Checkpoints: ``<out>/b7_checkpoints/<model>.ckpt`` is reused when present and trained on this
scenario (e.g. copied from ``rflscm train --config quick``); otherwise the model is trained on all
round-1 data at the benchmark's quick size (1500 steps of 32 pairs, the B1 quick overrides) or the
``full`` preset, and saved there.  Rendered APS are cached beside them (``<model>_aps.pt``).
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rflscm.bench import BenchContext, register_bench
from rflscm.bench.harness import BenchData, bench_size, build_model, scenario_path

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.eval.cache import ScenarioAPS
    from rflscm.models.source import APSSource
    from rflscm.network.kpi import KPIConfig
    from rflscm.network.optimize import OptimizeResult
    from rflscm.network.space import SearchSpace

MODELS = ("rflscm", "nerf2", "wnomp")
KEYS = ("coverage", "mean_sinr_db", "p5_sinr_db", "overlap")


@register_bench(
    "b7",
    "network optimisation: true vs predicted coverage/SINR gain of each model's recommendation",
)
def run(ctx: BenchContext) -> dict[str, Any]:
    from rflscm.data import load_scenario

    path, source = scenario_path(ctx)
    full = load_scenario(path)
    size = dataclasses.replace(bench_size(ctx.size), max_sites=None, max_grids=None, crop_margin_m=None)
    data = BenchData(
        full,
        full,
        None,
        size,
        {"scenario": str(path), "source": source, "name": full.meta.name},
    )
    return run_b7(ctx, data, MODELS)


def run_b7(ctx: BenchContext, data: BenchData, models: tuple[str, ...], restarts: int = 2) -> dict[str, Any]:
    from rflscm.network.kpi import KPIConfig
    from rflscm.network.space import build_space
    from rflscm.sim.truth import truth_folder

    scen = data.scenario
    truth_folder(scen)  # B7 needs truth/
    folder = Path(ctx.out_dir) / "b7_checkpoints"
    folder.mkdir(parents=True, exist_ok=True)
    space = build_space({}, scen.cells[1], scen.meta.codebooks)
    kpi = KPIConfig()
    out: dict[str, Any] = {
        "scenario": data.info,
        "size": data.size.describe(),
        "notes": __doc__.split("\n\n")[-1],
        "search_space_log10": space.size_log10(),
        "kpi": kpi.describe(list(scen.meta.frequencies_hz)),
        "models": {},
    }
    runs: dict[str, tuple[OptimizeResult, ScenarioAPS]] = {}
    for name in ("oracle", *models):
        model, train_s, reused = _model(ctx, data, name, folder)
        entry, result, cache = _optimise(scen, model, space, kpi, folder / f"{name}_aps.pt", restarts)
        entry.update(train_time_s=train_s, checkpoint_reused=reused)
        out["models"][name] = entry
        runs[name] = (result, cache)
    oracle_gain = out["models"]["oracle"]["true_gain"]["coverage"]
    for entry in out["models"].values():
        entry["share_of_oracle_true_coverage_gain"] = (
            entry["true_gain"]["coverage"] / oracle_gain if oracle_gain else None
        )
    out["optimisers_on_oracle"] = _compare_optimisers(scen, runs["oracle"], space, kpi)
    learned = {k: v for k, v in out["models"].items() if k != "oracle"}
    best = max(learned, key=lambda k: learned[k]["true_gain"]["coverage"])
    out["winner"] = (
        f"{best}: its recommendation gains {100 * learned[best]['true_gain']['coverage']:+.2f} % true "
        f"coverage, {100 * (learned[best]['share_of_oracle_true_coverage_gain'] or 0):.0f} % of the "
        f"oracle's {100 * oracle_gain:+.2f} %"
    )
    return out


def _model(ctx: BenchContext, data: BenchData, name: str, folder: Path) -> tuple[APSSource, float, bool]:
    from rflscm.errors import CheckpointError
    from rflscm.models import load_model

    if name == "oracle":
        from rflscm.eval.oracle import OracleModel

        t0 = time.perf_counter()
        oracle = OracleModel.for_scenario(data.scenario, data.size.grid(), ctx.device)
        return oracle, time.perf_counter() - t0, False
    path = folder / f"{name}.ckpt"
    if path.is_file():
        try:
            model = load_model(path, data.scenario, device=ctx.device)
            return (
                model,
                float(model.run_info.get("fit", {}).get("train_time_s", float("nan"))),
                True,
            )
        except CheckpointError:
            pass
    from rflscm.eval import fit_with_protocol

    model = build_model(data, name, device=ctx.device)
    t0 = time.perf_counter()
    fit_with_protocol(model, data.scenario, None, progress=False)
    elapsed = time.perf_counter() - t0
    model.run_info["fit"] = {"train_time_s": elapsed}
    model.save(path)
    return model, elapsed, False


def _optimise(
    scen: Scenario, model: APSSource, space: SearchSpace, kpi: KPIConfig, cache_path: Path, restarts: int
) -> tuple[dict[str, Any], OptimizeResult, ScenarioAPS]:
    from rflscm.eval.cache import APSCacheError, load_or_render
    from rflscm.network.optimize import run_optimize

    if model.name == "oracle":
        cache_path.unlink(missing_ok=True)  # the truth is cheap to read
    try:
        cache, cache_s = load_or_render(model, scen, cache_path)
    except APSCacheError:  # B7's own cache of an earlier checkpoint (retrained): render again
        cache_path.unlink(missing_ok=True)
        cache, cache_s = load_or_render(model, scen, cache_path)
    result = run_optimize(scen, cache, space, 1, "coverage", "cd", kpi, verify=True, restarts=restarts)
    s = result.summary()
    entry = {
        "kpi_pairs": s["kpi_pairs"],
        "predicted_before": {k: s["predicted"]["before"][k] for k in KEYS},
        "predicted_gain": {k: s["predicted_gain"][k] for k in KEYS},
        "true_before": {k: s["truth"]["before"][k] for k in KEYS},
        "true_after": {k: s["truth"]["after"][k] for k in KEYS},
        "true_gain": {k: s["true_gain"][k] for k in KEYS},
        "changed_cells": s["changed_cells"],
        "evaluations": s["search"]["evaluations"],
        "candidates_per_s": s["search"]["candidates_per_s"],
        "aps_time_s": cache_s,
        "search_time_s": result.timings["search_s"],
        "verify_time_s": result.timings["verify_s"],
        "kept_bins_mean": float(np.mean([len(b) for b in cache.bins])),
    }
    return entry, result, cache


def _compare_optimisers(
    scen: Scenario, oracle_run: tuple[OptimizeResult, ScenarioAPS], space: SearchSpace, kpi: KPIConfig
) -> dict[str, Any]:
    """Coordinate descent against scipy DE on the oracle's APS, DE given CD's wall time."""
    from rflscm.network.search import NetworkEvaluator, differential_evolution

    cd, cache = oracle_run
    ev = NetworkEvaluator(scen, 1, cache, space, kpi, "coverage")
    de = differential_evolution(ev, time_budget_s=max(cd.search.time_s, 5.0), seed=0)
    out = {}
    for label, r in (
        ("coordinate_descent", cd.search),
        ("scipy_differential_evolution", de),
    ):
        out[label] = {
            "objective_before": r.base_objective,
            "objective_after": r.objective,
            "evaluations": r.evaluations,
            "time_s": r.time_s,
            "gain_per_1000_evaluations": 1000 * (r.objective - r.base_objective) / max(r.evaluations, 1),
        }
    return out
