"""Import — WNOMP and RF-LSCM on an imported scenario against the scenario its raw samples came from (issue 25).

The source scenario (``--scenario``, else the shipped default) is written as raw samples by the simulator's raw
writer (``rflscm simulate --raw-out``: every reported (round, cell, grid, beam) value becomes
:data:`RAW_SAMPLES` samples at UE positions jittered inside the grid, one log-normal fading draw of
σ = :data:`FADING_DB` dB and unit linear mean each; the cell list; the point cloud) and imported again with
``rflscm import``'s defaults (``import_raw``: 10 m bins, MAD outliers, 3 samples minimum, the default
threshold).  Both scenarios then go through the same benchmark: the size's sub-scenario (``quick``: the site
B1 picks and the 150 measured grids nearest it), WNOMP (settings chosen on held-aside round-1 beams) and
RF-LSCM (the size's steps, seeded alike), the adjust protocol (train on round 1, predict round 2).

What is compared: each model's round-2 MAE against *its own scenario's* round-2 reports, per row (SSB/CSI-RS,
all/changed cells), and ``imported − source``.  The imported grids are the bins of the samples: they have their
own ids, their centres are the source grids' (the writer jitters inside the grid square), and their values are
linear means of faded samples of the source values, so the two test sets are the same beams measured twice,
not the same numbers (``test_beams`` counts each; the source's oracle is its floor, the imported scenario has no
truth).  The raw writer writes every round, so the imported scenario has its own round 2.
"""

from __future__ import annotations

import dataclasses
import shutil
import time
from pathlib import Path
from typing import Any

from rflscm.bench import BenchContext, register_bench
from rflscm.bench.harness import BenchData, BenchSize, bench_size, load_bench_data, scenario_path, train_and_evaluate
from rflscm.bench.report import header, mae_summary, seeds_of
from rflscm.data import BEAM_TYPES
from rflscm.errors import ConfigError
from rflscm.eval import AdjustProtocol

RAW_SAMPLES = 10
"""Raw samples per reported beam (the documented round trip's `--raw-samples 10`)."""
FADING_DB = 2.0
"""Per-sample log-normal fading σ [dB] (`--raw-fading`'s default)."""
MODELS = ("wnomp", "rflscm")
ROWS = [(bt, which) for bt in BEAM_TYPES for which in ("all", "changed")]
RAW_DIR, IMPORTED_DIR = "import_raw", "import_scenario"


@register_bench("import", "WNOMP and RF-LSCM on a scenario imported from raw samples against the source scenario")
def run(ctx: BenchContext) -> dict[str, Any]:
    return run_import(ctx, bench_size(ctx.size))


def run_import(ctx: BenchContext, size: BenchSize, models: tuple[str, ...] = MODELS) -> dict[str, Any]:
    """The benchmark at ``size`` (tests pass ``tiny_size()``); writes ``import_raw/`` and ``import_scenario/``
    under ``ctx.out_dir``."""
    imported, made = _raw_and_import(ctx)
    arms = {
        "source": load_bench_data(ctx, size),
        "imported": load_bench_data(dataclasses.replace(ctx, scenario=str(imported)), size),
    }
    seeds = seeds_of(ctx)
    out = header(ctx, arms["source"], seeds, __doc__.split("\n\n")[-1].strip())
    out["import"] = made
    out["arms"] = {name: _describe(data) for name, data in arms.items()}
    results: dict[str, dict[str, Any]] = {}
    for model in models:
        results[model] = {}
        for arm, data in arms.items():
            run = train_and_evaluate(data, model, AdjustProtocol(), seed=seeds[0], device=ctx.device)
            summary = mae_summary(run.metrics)
            results[model][arm] = {
                "mae_db": summary["model"],
                "train_time_s": run.train_time_s,
                "steps": run.fit.get("steps"),
                "test_beams": {bt: run.metrics["counts"][bt]["beams"] for bt in BEAM_TYPES},
            }
            if arm == "source":
                out.setdefault("source_oracle_mae_db", summary["oracle"])
            out.setdefault("trivial_mae_db", {})[arm] = summary["trivial"]
        results[model]["imported_minus_source_db"] = _diff(results[model]["imported"], results[model]["source"])
    out["models"] = results
    out["table"] = _table(results)
    out["plots"] = []
    return out


def _raw_and_import(ctx: BenchContext) -> tuple[Path, dict[str, Any]]:
    """Write the raw files of the source scenario and import them; the imported folder and what was done."""
    from rflscm.data import load_scenario
    from rflscm.data.ingest import import_raw, load_spec
    from rflscm.sim.raw_writer import write_raw

    path, _ = scenario_path(ctx)
    raw, imported = Path(ctx.out_dir) / RAW_DIR, Path(ctx.out_dir) / IMPORTED_DIR
    for folder, marker in ((raw, "import.yaml"), (imported, "scenario.yaml")):
        if folder.exists():  # an earlier run's output: only ever a folder this benchmark wrote
            if not (folder / marker).is_file():
                raise ConfigError(f"{folder} exists and is not an earlier `bench import` output; choose another --out.")
            shutil.rmtree(folder)
    source = load_scenario(path)
    grid_m = float(source.meta.simulation.get("config", {}).get("grid_size_m", 10.0))
    t0 = time.perf_counter()
    written = write_raw(source, raw, samples_per_beam=RAW_SAMPLES, fading_db=FADING_DB, grid_size_m=grid_m)
    t1 = time.perf_counter()
    res = import_raw(load_spec(raw / "import.yaml", {}), imported)
    load_scenario(imported)  # what `rflscm import` checks before it keeps the folder
    t2 = time.perf_counter()
    made = {
        "raw": {**written, "samples_per_beam": RAW_SAMPLES, "fading_db": FADING_DB, "time_s": t1 - t0},
        "import": {
            "samples_read": res.samples_read,
            "samples_kept": res.samples_kept,
            "dropped": dict(res.dropped.samples),
            "bins": res.bins,
            "grids": res.grids,
            "threshold_dbm": res.threshold_dbm,
            "point_cloud_points": res.point_cloud_points,
            "time_s": t2 - t1,
        },
    }
    return imported, made


def _describe(data: BenchData) -> dict[str, Any]:
    m = data.scenario.measurements
    reported = m[m["rsrp_dbm"].notna().to_numpy()]
    return {
        "scenario": data.info["scenario"],
        "sites": data.info["sites"],
        "cells": len(data.info["cells"]),
        "grids": data.info["grids"],
        "reported_beams": {str(r): int((reported["round"] == r).sum()) for r in sorted(reported["round"].unique())},
        "threshold_dbm": data.scenario.meta.rsrp_threshold_dbm,
        "point_cloud_points": data.info["point_cloud_points"],
    }


def _diff(a: dict[str, Any], b: dict[str, Any]) -> dict[str, dict[str, float | None]]:
    out: dict[str, dict[str, float | None]] = {bt: {} for bt in BEAM_TYPES}
    for bt, which in ROWS:
        x, y = a["mae_db"][bt][which], b["mae_db"][bt][which]
        out[bt][which] = None if x is None or y is None else x - y
    return out


def _table(results: dict[str, dict[str, Any]]) -> list[str]:
    """Markdown rows: model, arm, the four MAEs (and the difference rows)."""
    lines = ["| model | scenario | SSB all | SSB changed | CSI all | CSI changed |", "|---|---|---|---|---|---|"]
    for model, arms in results.items():
        for arm in ("source", "imported"):
            cells = [arms[arm]["mae_db"][bt][w] for bt, w in ROWS]
            lines.append(f"| {model} | {arm} | " + " | ".join(_fmt(v) for v in cells) + " |")
        diff = [arms["imported_minus_source_db"][bt][w] for bt, w in ROWS]
        lines.append(f"| {model} | imported − source | " + " | ".join(_fmt(v, signed=True) for v in diff) + " |")
    return lines


def _fmt(value: float | None, signed: bool = False) -> str:
    if value is None:
        return "—"
    return f"{value:+.2f}" if signed else f"{value:.2f}"
