"""B1 — multi-cell antenna adjustment (paper §V-B, SPEC §5): RF-LSCM, NeRF²-LSCM, WNOMP and the oracle.

Every model trains on all round-1 measurements of the benchmark scenario and predicts round 2 (the
changed antenna configuration, through A′).  Reported per model: MAE [dB] for SSB and CSI-RS, over
all cells and over the changed cells, next to the oracle (true APS through A′: the floor left by
angular binning and noise) and the trivial baseline; training time; peak memory while fitting
(CPU RSS, or CUDA ``max_memory_allocated``); inference throughput of the field models (rays ×
samples per second, see :func:`~rflscm.bench.harness.render_throughput`) and their training
decoder evaluations per second.

Sizes (:mod:`rflscm.bench.harness`): ``quick`` = one site (6 cells, 2 carriers), 150 grids, the
paper's 91 × 72 angle grid, 1500 steps of 32 pairs per field model (NeRF² at its quick preset's
shrunk widths), on 2 CPU cores; ``full`` = the whole scenario and the models' ``full`` presets, for
a GPU.  Seeds: each field model is trained once per seed; MAEs are averaged (WNOMP: first seed).  WNOMP's
settings are chosen on held-aside round-1 beams, as ``rflscm demo`` chooses them (``settings`` in its entry).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rflscm.bench import BenchContext, register_bench
from rflscm.bench.harness import BenchData, BenchSize, bench_size, load_bench_data, train_and_evaluate
from rflscm.bench.measure import parameter_count, render_throughput
from rflscm.bench.report import aggregate, header, mae_summary, new_figure, record, save_figure, seeds_of
from rflscm.data import BEAM_TYPES
from rflscm.eval import AdjustProtocol

MODELS = ("rflscm", "nerf2", "wnomp")


@register_bench(
    "b1", "multi-cell antenna adjustment: RF-LSCM, NeRF²-LSCM, WNOMP, oracle (MAE, time, memory, throughput)"
)
def run(ctx: BenchContext) -> dict[str, Any]:
    return run_b1(ctx, bench_size(ctx.size))


def run_b1(ctx: BenchContext, size: BenchSize) -> dict[str, Any]:
    data = load_bench_data(ctx, size)
    seeds = seeds_of(ctx)
    out = header(ctx, data, seeds, __doc__.split("\n\n")[-1].strip())
    models: dict[str, Any] = {}
    reference: dict[str, Any] = {}
    seen_metrics: dict[str, Any] = {}  # the first model's MAE blocks over the pairs with round-1 reports
    for name in MODELS:
        runs = [
            train_and_evaluate(data, name, AdjustProtocol(), seed=s, device=ctx.device)
            for s in (seeds if name != "wnomp" else seeds[:1])
        ]
        models[name] = _model_entry(data, runs)
        reference = reference or mae_summary(runs[0].metrics)
        reference["counts"] = runs[0].metrics["counts"]
        seen_metrics = seen_metrics or runs[0].metrics.get("seen") or {}
    out["models"] = models
    out["oracle"] = {"mae_db": reference["oracle"]}
    out["trivial"] = {"mae_db": reference["trivial"]}
    # the pairs with round-1 reports, which every model answers: one set of pairs for the models' ``seen_mae_db``
    seen = mae_summary(seen_metrics)
    out["seen"] = {"oracle": seen["oracle"], "trivial": seen["trivial"]}
    out["changed_cells"] = reference["counts"]["changed_cells"]
    out["test_beams"] = {bt: reference["counts"][bt]["beams"] for bt in BEAM_TYPES}
    out["plots"] = [_plot(ctx, models, out["oracle"], out["trivial"])]
    return out


def _model_entry(data: BenchData, runs: list[Any]) -> dict[str, Any]:
    agg = aggregate([record(r) for r in runs])
    mean, std = agg["mean"], agg["std"]
    first = runs[0]
    entry = {
        "mae_db": mean["mae_db"],
        "mae_db_std": std["mae_db"],
        "seen_mae_db": mean["seen_mae_db"],
        "train_time_s": mean["train_time_s"],
        "steps": mean["steps"],
        "peak_memory_mb": mean["peak_memory_mb"],
        "memory_increase_mb": mean["memory_increase_mb"],
        "memory_kind": first.memory["kind"],
        "parameters": parameter_count(first.model),
        "throughput": render_throughput(first.model, data),
        "train_decoder_evals_per_s": first.fit.get("decoder_evals_per_s"),
        "fit_pairs_per_s": first.fit.get("pairs_per_s"),
        "runs": len(runs),
    }
    if "wnomp_selection" in first.model.run_info:
        entry["settings"] = first.model.run_info["wnomp_selection"]["chosen"]
    return entry


def _plot(ctx: BenchContext, models: dict[str, Any], oracle: dict[str, Any], trivial: dict[str, Any]) -> str:
    fig, (ax,) = new_figure(width=8.0)
    groups = [("ssb", "all"), ("ssb", "changed"), ("csi", "all"), ("csi", "changed")]
    series = {name: e["mae_db"] for name, e in models.items()} | {
        "oracle": oracle["mae_db"],
        "trivial": trivial["mae_db"],
    }
    width = 0.8 / len(series)
    x = np.arange(len(groups))
    for i, (name, mae) in enumerate(series.items()):
        values = [(mae or {}).get(bt, {}).get(which) for bt, which in groups]
        ax.bar(x + i * width, [np.nan if v is None else v for v in values], width, label=name)
    ax.set_xticks(x + 0.4 - width / 2, [f"{bt.upper()} {which}" for bt, which in groups])
    ax.set_ylabel("MAE after adjustment [dB]")
    ax.set_title("B1 multi-cell antenna adjustment")
    ax.legend()
    return save_figure(fig, ctx, "b1_mae")
