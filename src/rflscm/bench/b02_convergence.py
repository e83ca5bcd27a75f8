"""B2 — convergence: validation MAE vs wall time for RF-LSCM and NeRF²-LSCM, each with and without
HiTAM (paper §VI-A, Fig. "nerf-rflscm-wohitam"), mean ± std over ``--seeds`` seeds.

Each variant trains with the same time budget; every ``val_every`` steps the benchmark measures the
MAE [dB] on the held-aside round-1 beams (``model.validation_mae()``; the trainer's own periodic
validation is switched off) and that measurement is *not* counted as training time.  Curves are
put on a common time axis (the last measured value holds until the next) and averaged over seeds.
``target_mae_db`` = the lowest point of any variant's mean curve + ``target_margin_db`` (a level the
best variant reached, so it is well below the untrained MAE); ``time_to_target_s`` is when a seed's
curve first reaches it (mean over the seeds that do; ``reached`` counts them), and
``hitam_speedup`` = time to target without HiTAM / with HiTAM (``null`` unless both reach it).
The paper plots the MAE on the other measurement round; here the final round-2 (adjust protocol)
MAE of every run is reported beside the curves.

Sizes: ``quick`` = the B1 quick scenario and models (one site, 150 grids, 91 × 72 angles, 32 pairs
per step) with a 400-step schedule (learning-rate decay; HiTAM warm-up 150, ramp 40, so that the
HiTAM variants reach the refinement stage within the budget), 90 s of training per variant and
seed (validation every 20 steps on 64 pairs), 2 CPU cores; ``full`` = the whole scenario and
``full`` presets, each variant trained for its full step count.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from rflscm.bench import BenchContext, register_bench
from rflscm.bench.harness import BenchSize, bench_size, field_model, load_bench_data, merge, train_and_evaluate
from rflscm.bench.report import aggregate, header, mean_std, new_figure, record, save_figure, seeds_of
from rflscm.eval import AdjustProtocol

if TYPE_CHECKING:
    from rflscm.models.base import LSCMModel

VARIANTS = {
    "rflscm_hitam": ("rflscm", {}),
    "rflscm_no_hitam": ("rflscm", {"hitam": {"enabled": False}}),
    "nerf2_hitam": ("nerf2", {}),
    "nerf2_no_hitam": ("nerf2", {"hitam": {"enabled": False}}),
}
SETTINGS: dict[str, dict[str, Any]] = {  # per size: time budget per run [s] (None: the full step count),
    # validation every N steps, and overrides on top of the size's (steps: the learning-rate schedule's length)
    "tiny": {"time_budget_s": None, "val_every": 2, "extra": {}},
    "quick": {
        "time_budget_s": 90.0,
        "val_every": 20,
        "extra": {"train": {"steps": 400}, "hitam": {"warmup_steps": 150, "ramp_steps": 40}},
    },
    "full": {"time_budget_s": None, "val_every": 100, "extra": {}},
}
TARGET_MARGIN_DB = 1.0
GRID_POINTS = 60


@register_bench(
    "b2", "convergence: validation MAE vs wall time, RF-LSCM and NeRF²-LSCM with/without HiTAM, several seeds"
)
def run(ctx: BenchContext) -> dict[str, Any]:
    return run_b2(ctx, bench_size(ctx.size))


def run_b2(ctx: BenchContext, size: BenchSize) -> dict[str, Any]:
    data = load_bench_data(ctx, size)
    seeds = seeds_of(ctx)
    settings = SETTINGS[size.name]
    budget, every = settings["time_budget_s"], settings["val_every"]
    out = header(ctx, data, seeds, __doc__.split("\n\n")[-1].strip())
    out["settings"] = {**settings, "target_margin_db": TARGET_MARGIN_DB}
    variants: dict[str, Any] = {}
    for key, (model, variant) in VARIANTS.items():
        extra = merge(merge(settings["extra"], variant), {"train": {"val_every": 10**9}})
        runs, curves = [], []
        for seed in seeds:
            curve: list[tuple[float, float, float]] = []

            def on_step(m: LSCMModel, row: dict[str, float], curve: list = curve) -> None:
                if row["step"] % every == 0 or row["step"] == 1:
                    curve.append((row["time_s"], row["step"], float(field_model(m).validation_mae())))

            r = train_and_evaluate(
                data, model, AdjustProtocol(), extra, seed, ctx.device, on_step=on_step, time_budget_s=budget
            )
            curve.append((r.history[-1]["time_s"], r.history[-1]["step"], float(field_model(r.model).validation_mae())))
            runs.append(r)
            curves.append(curve)
        variants[key] = {"curves": curves, "runs": [record(r) for r in runs]}
    return _summarise(ctx, out, variants)


def _summarise(ctx: BenchContext, out: dict[str, Any], variants: dict[str, Any]) -> dict[str, Any]:
    curves = {k: _mean_curve(v["curves"]) for k, v in variants.items()}
    best = [float(np.nanmin(m)) for _, m, _ in curves.values() if np.isfinite(m).any()]
    target = min(best) + TARGET_MARGIN_DB if best else None
    out["target_mae_db"] = target
    table: dict[str, Any] = {}
    for key, v in variants.items():
        agg = aggregate(v["runs"])
        times = [_time_to(c, target) for c in v["curves"]]
        reached = [t for t in times if t is not None]
        grid, mean, std = curves[key]
        table[key] = {
            "initial_val_mae_db": mean_std([c[0][2] for c in v["curves"]]),
            "best_val_mae_db": float(np.nanmin(mean)) if np.isfinite(mean).any() else None,
            "final_val_mae_db": mean_std([c[-1][2] for c in v["curves"]]),
            "time_to_target_s": mean_std(reached),
            "reached": len(reached),
            "steps": agg["mean"]["steps"],
            "train_time_s": agg["mean"]["train_time_s"],
            "round2_mae_db": agg["mean"]["mae_db"],
            "curve": {"time_s": grid.tolist(), "mae_mean_db": mean.tolist(), "mae_std_db": std.tolist()},
            "raw_curves": [[list(p) for p in c] for c in v["curves"]],
        }
    out["variants"] = table
    out["hitam_speedup"] = {
        m: _ratio(table[f"{m}_no_hitam"]["time_to_target_s"]["mean"], table[f"{m}_hitam"]["time_to_target_s"]["mean"])
        for m in ("rflscm", "nerf2")
    }
    out["plots"] = [_plot(ctx, table, target)]
    return out


def _time_to(curve: list[tuple[float, float, float]], target: float | None) -> float | None:
    if target is None:
        return None
    for t, _, mae in curve:
        if np.isfinite(mae) and mae <= target:
            return float(t)
    return None


def _mean_curve(curves: list[list[tuple[float, float, float]]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Seeds' curves on a common time grid up to the shortest run (previous-value hold), mean and std."""
    end = min(c[-1][0] for c in curves)
    grid = np.linspace(0.0, end, GRID_POINTS)
    rows = []
    for c in curves:
        t = np.array([p[0] for p in c])
        v = np.array([p[2] for p in c])
        pos = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, len(t) - 1)
        rows.append(v[pos])
    values = np.array(rows)
    return grid, np.nanmean(values, 0), np.nanstd(values, 0)


def _ratio(slow: float | None, fast: float | None) -> float | None:
    return None if slow is None or fast is None or fast <= 0 else float(slow / fast)


def _plot(ctx: BenchContext, table: dict[str, Any], target: float | None) -> str:
    fig, (ax,) = new_figure(width=7.0)
    for key, entry in table.items():
        t = np.array(entry["curve"]["time_s"])
        m = np.array(entry["curve"]["mae_mean_db"])
        s = np.array(entry["curve"]["mae_std_db"])
        (line,) = ax.plot(t, m, label=key.replace("_", " "), linestyle="-" if "no_hitam" not in key else "--")
        ax.fill_between(t, m - s, m + s, color=line.get_color(), alpha=0.2)
    if target is not None:
        ax.axhline(target, color="grey", linewidth=0.8, linestyle=":", label=f"target {target:.1f} dB")
    ax.set_xlabel("training wall time [s]")
    ax.set_ylabel("validation MAE [dB]")
    ax.set_title("B2 convergence (mean ± std over seeds)")
    ax.legend()
    return save_figure(fig, ctx, "b2_convergence")
