"""B6 — unseen grids and APS recovery against the ray-traced truth (SPEC §5, paper §V-B, unseen grids).

Under :class:`~rflscm.eval.UnseenProtocol` (a seeded 20 % of the measured grids held out entirely)
RF-LSCM, NeRF²-LSCM and WNOMP train on the rest (WNOMP's settings chosen on held-aside round-1 beams of
the training grids).  Reported per model:

* ``unseen_mae_db.{ssb,csi}``: MAE [dB] of the round-1 RSRP at the held-out grids (``null`` for
  WNOMP, which has no notion of a grid it never measured), next to the oracle and trivial MAE;
* ``aps_unseen``: APS recovery at the held-out grids against the true (binned ray-traced) APS — the
  mean and median over pairs of the per-pair NMSE [dB] and the power-weighted angular error [deg]
  of the 5 strongest bins (field models), as ``rflscm evaluate`` reports them;
* ``aps_seen``: the same on a seeded sample of the training pairs with a reported beam (quick 200,
  full 2000) — the recovery WNOMP is built for.

Sizes: ``quick`` = the B1 quick scenario and models (one site, 150 grids → 30 held out, 91 × 72
angles, 1500 steps of 32 pairs) on 2 CPU cores; ``full`` = the whole scenario and ``full`` presets.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rflscm.bench import BenchContext, register_bench
from rflscm.bench.harness import BenchSize, bench_size, load_bench_data, train_and_evaluate
from rflscm.bench.measure import aps_recovery
from rflscm.bench.report import aggregate, header, new_figure, save_figure, seeds_of
from rflscm.data import BEAM_TYPES
from rflscm.data.measurements import reported_pairs
from rflscm.eval import UnseenProtocol

MODELS = ("rflscm", "nerf2", "wnomp")
HOLDOUT = 0.2
APS_SEEN_PAIRS = {"tiny": 20, "quick": 200, "full": 2000}


@register_bench("b6", "unseen grids and APS recovery vs ray-traced truth: RF-LSCM, NeRF²-LSCM, WNOMP")
def run(ctx: BenchContext) -> dict[str, Any]:
    return run_b6(ctx, bench_size(ctx.size))


def run_b6(ctx: BenchContext, size: BenchSize) -> dict[str, Any]:
    data = load_bench_data(ctx, size)
    seeds = seeds_of(ctx)
    protocol = UnseenProtocol(fraction=HOLDOUT, seed=0)
    out = header(ctx, data, seeds, __doc__.split("\n\n")[-1].strip())
    out["holdout_fraction"] = HOLDOUT
    out["holdout_grids"] = int(len(protocol.held_out(data.scenario)))
    seen_pairs = reported_pairs(protocol.training_scenario(data.scenario).measurements)
    models: dict[str, Any] = {}
    reference: dict[str, Any] = {}
    for name in MODELS:
        entries = []
        for seed in seeds if name != "wnomp" else seeds[:1]:
            r = train_and_evaluate(data, name, protocol, seed=seed, device=ctx.device)
            m = r.metrics
            aps = m.get("aps") or {}
            entries.append(
                {
                    "unseen_mae_db": dict(m["unseen"]["mae_db"]),
                    "aps_unseen": {k: aps.get(k) for k in ("nmse_db", "nmse_db_median", "angle_error_deg", "pairs")},
                    "aps_seen": aps_recovery(r.judged, data.oracle, seen_pairs, max_pairs=APS_SEEN_PAIRS[size.name]),
                    "train_time_s": r.train_time_s,
                }
            )
            reference = reference or m
        models[name] = {**aggregate(entries)["mean"], "runs": len(entries)}
        if "wnomp_selection" in r.model.run_info:
            models[name]["settings"] = r.model.run_info["wnomp_selection"]["chosen"]
    out["models"] = models
    out["oracle"] = {"unseen_mae_db": dict(reference["unseen"]["oracle_mae_db"])}
    out["trivial"] = {"unseen_mae_db": dict(reference["unseen"]["trivial_mae_db"])}
    out["plots"] = [_plot(ctx, models, out["oracle"], out["trivial"])]
    return out


def _plot(ctx: BenchContext, models: dict[str, Any], oracle: dict[str, Any], trivial: dict[str, Any]) -> str:
    fig, axes = new_figure(ncols=3, width=4.5)
    names = list(models)
    x = np.arange(len(names))
    for i, bt in enumerate(BEAM_TYPES):
        vals = [models[n]["unseen_mae_db"].get(bt) for n in names]
        axes[0].bar(x + 0.4 * i, [np.nan if v is None else v for v in vals], 0.4, label=bt.upper())
        for ref, style in ((oracle, ":"), (trivial, "--")):
            if ref["unseen_mae_db"].get(bt) is not None:
                axes[0].axhline(ref["unseen_mae_db"][bt], linestyle=style, linewidth=0.8, color=f"C{i}")
    axes[0].set_xticks(x + 0.2, names)
    axes[0].set_ylabel("MAE at unseen grids [dB] (: oracle, -- trivial)")
    axes[0].legend()
    for ax, metric, label in (
        (axes[1], "nmse_db", "APS NMSE [dB]"),
        (axes[2], "angle_error_deg", "APS angle error [deg]"),
    ):
        for i, where in enumerate(("aps_seen", "aps_unseen")):
            vals = [models[n][where].get(metric) for n in names]
            ax.bar(x + 0.4 * i, [np.nan if v is None else v for v in vals], 0.4, label=where.replace("aps_", ""))
        ax.set_xticks(x + 0.2, names)
        ax.set_ylabel(label)
        ax.legend()
    fig.suptitle("B6 unseen grids and APS recovery")
    return save_figure(fig, ctx, "b6_unseen")
