"""B5 — the missing-beam penalty weight α_P (paper §VI-B, Fig. "ablation_alpha_p"): α_P ∈ {0, 0.1, 0.5, 1, 2}
(the plumbing tests' ``tiny`` size: {0, 0.5}).

RF-LSCM (``loss.missing_penalty`` = α_P, everything else at the size's settings) trains on all
round-1 data and predicts round 2 (adjust protocol).  Reported per α_P: MAE [dB] (SSB, CSI-RS; all
and changed cells), the final validation MAE on held-aside round-1 beams, and the share of the
*missing* round-2 beams that the model predicts above their bound under the reporting rule (what
L_P penalises; lower is better; ``evaluate``'s ``missing_above_bound.*.pooled`` over the scored test
pairs), next to the oracle's, and the MAE against the noiseless truth over
every beam above r_th, reported or not (``truth_mae_db``: free of which beams the rule let through).

Sizes: ``quick`` = the B1 quick scenario and RF-LSCM settings (one site, 150 grids, 91 × 72
angles, 32 pairs per step) with 400 steps (HiTAM warm-up 160, ramp 40) on 2 CPU cores; ``full`` =
the whole scenario and the ``full`` preset.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rflscm.bench import BenchContext, register_bench
from rflscm.bench.harness import BenchSize, bench_size, load_bench_data, merge, train_and_evaluate
from rflscm.bench.report import aggregate, header, mae_summary, new_figure, record, save_figure, seeds_of
from rflscm.data import BEAM_TYPES
from rflscm.eval import AdjustProtocol

EXTRA = {  # size → RF-LSCM overrides on top of the size's
    "tiny": {},
    "quick": {"train": {"steps": 400}, "hitam": {"warmup_steps": 160, "ramp_steps": 40}},
    "full": {},
}
ALPHAS = {"tiny": (0.0, 0.5), "quick": (0.0, 0.1, 0.5, 1.0, 2.0), "full": (0.0, 0.1, 0.5, 1.0, 2.0)}


@register_bench("b5", "missing-beam penalty sweep: RF-LSCM with α_P ∈ {0, 0.1, 0.5, 1, 2}")
def run(ctx: BenchContext) -> dict[str, Any]:
    return run_b5(ctx, bench_size(ctx.size))


def run_b5(ctx: BenchContext, size: BenchSize) -> dict[str, Any]:
    data = load_bench_data(ctx, size)
    seeds = seeds_of(ctx)
    out = header(ctx, data, seeds, __doc__.split("\n\n")[-1].strip())
    alphas = ALPHAS[size.name]
    out["alphas"] = list(alphas)
    sweep: dict[str, Any] = {}
    reference: dict[str, Any] = {}
    oracle_above = None
    for alpha in alphas:
        runs = [
            train_and_evaluate(
                data,
                "rflscm",
                AdjustProtocol(),
                merge(EXTRA[size.name], {"loss": {"missing_penalty": alpha}}),
                s,
                ctx.device,
            )
            for s in seeds
        ]
        agg = aggregate([record(r) for r in runs])
        rates = [_above(r.metrics, "model") for r in runs]
        sweep[f"{alpha:g}"] = {
            "mae_db": agg["mean"]["mae_db"],
            "mae_std_db": agg["std"]["mae_db"],
            "truth_mae_db": agg["mean"]["truth_mae_db"],
            "val_mae_db": agg["mean"]["val_mae_db"],
            "missing_above_bound": float(np.mean([r for r in rates if r is not None]))
            if all(r is not None for r in rates)
            else None,
            "train_time_s": agg["mean"]["train_time_s"],
        }
        reference = reference or mae_summary(runs[0].metrics)
        if oracle_above is None:
            oracle_above = _above(runs[0].metrics, "oracle")
    out["sweep"] = sweep
    out["oracle"] = {
        "mae_db": reference["oracle"],
        "truth_mae_db": reference["truth"]["oracle"],
        "missing_above_bound": oracle_above,
    }
    out["trivial"] = {"mae_db": reference["trivial"], "truth_mae_db": reference["truth"]["trivial"]}
    out["best_alpha"] = {bt: _best(sweep, bt) for bt in BEAM_TYPES}
    out["best_alpha_truth"] = {bt: _best(sweep, bt, "truth_mae_db") for bt in BEAM_TYPES}
    out["plots"] = [_plot(ctx, sweep, reference["oracle"])]
    return out


def _above(metrics: dict[str, Any], who: str) -> float | None:
    """Share of the round-2 beams that were *not* reported that ``who`` (model, oracle) predicts above their bound
    under the scenario's reporting rule, SSB and CSI-RS pooled (``evaluate``'s ``missing_above_bound``): what
    L_P penalises."""
    return ((metrics.get("missing_above_bound") or {}).get(who) or {}).get("pooled")


def _best(sweep: dict[str, Any], bt: str, key: str = "mae_db") -> float | None:
    scored = [
        (e[key][bt]["all"], float(a)) for a, e in sweep.items() if (e[key] or {}).get(bt, {}).get("all") is not None
    ]
    return min(scored)[1] if scored else None


def _plot(ctx: BenchContext, sweep: dict[str, Any], oracle: dict[str, Any]) -> str:
    fig, axes = new_figure(ncols=2)
    alphas = [float(a) for a in sweep]
    for bt, marker in (("ssb", "o"), ("csi", "s")):
        axes[0].plot(alphas, [e["mae_db"][bt]["all"] for e in sweep.values()], marker=marker, label=f"{bt.upper()} all")
        axes[0].plot(
            alphas,
            [e["mae_db"][bt]["changed"] for e in sweep.values()],
            marker=marker,
            linestyle="--",
            label=f"{bt.upper()} changed",
        )
        if oracle[bt]["all"] is not None:
            axes[0].axhline(oracle[bt]["all"], color="grey", linestyle=":", linewidth=0.8)
    axes[0].set_xlabel("α_P")
    axes[0].set_ylabel("MAE after adjustment [dB]")
    axes[0].legend()
    for bt, marker in (("ssb", "o"), ("csi", "s")):
        values = [(e["truth_mae_db"] or {}).get(bt, {}).get("all") for e in sweep.values()]
        axes[1].plot(alphas, [np.nan if v is None else v for v in values], marker=marker, label=f"{bt.upper()} all")
    axes[1].set_xlabel("α_P")
    axes[1].set_ylabel("MAE vs noiseless truth, every beam ≥ r_th [dB]")
    axes[1].legend()
    fig.suptitle("B5 α_P sweep (grey: oracle)")
    return save_figure(fig, ctx, "b5_alpha_p")
