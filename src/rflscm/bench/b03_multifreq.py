"""B3 — multi-frequency channel modelling (paper §V-C, SPEC §5): RF-LSCM trained on p % of the 2.1 GHz
grids with and without all the 3.5 GHz data, tested on a fixed 70 % of the 2.1 GHz grids.

:class:`~rflscm.eval.MultiFreqProtocol` (test fraction 0.7, the lowest carrier, split seed 0) for
p ∈ {3, 5, 10, 20, 30}; the draws are nested, so a larger p adds grids to a smaller p's.  Reported:
MAE [dB] (SSB, CSI-RS) on the test grids per p and arm, next to the trivial baseline of that arm's
training data (each test pair gets its cell's mean training RSRP) and the oracle, and the gain of the
3.5 GHz data, ``gain_db[p] = MAE(without) − MAE(with)`` (positive: the other band helps), also in %.

Sizes: ``quick`` = the B1 quick scenario (one site: 3 cells per carrier, 150 grids, so p = 3 % is
4 grids), RF-LSCM with 200 steps of 32 pairs (HiTAM warm-up 80, ramp 20), 2 CPU cores;
``full`` = the whole scenario and the ``full`` preset.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from rflscm.bench import BenchContext, register_bench
from rflscm.bench.harness import BenchSize, bench_size, load_bench_data, train_and_evaluate
from rflscm.bench.report import aggregate, header, mae_summary, new_figure, record, save_figure, seeds_of
from rflscm.data import BEAM_TYPES
from rflscm.eval import MultiFreqProtocol

PERCENTS = {"tiny": (5.0, 30.0), "quick": (3.0, 5.0, 10.0, 20.0, 30.0), "full": (3.0, 5.0, 10.0, 20.0, 30.0)}
ARMS = {"with_other_band": True, "without_other_band": False}
EXTRA = {  # size → RF-LSCM overrides on top of the size's
    "tiny": {},
    "quick": {"train": {"steps": 200}, "hitam": {"warmup_steps": 80, "ramp_steps": 20}},
    "full": {},
}


@register_bench("b3", "multi-frequency: RF-LSCM on p % of 2.1 GHz grids with/without the 3.5 GHz data")
def run(ctx: BenchContext) -> dict[str, Any]:
    return run_b3(ctx, bench_size(ctx.size))


def run_b3(ctx: BenchContext, size: BenchSize) -> dict[str, Any]:
    data = load_bench_data(ctx, size)
    seeds = seeds_of(ctx)
    out = header(ctx, data, seeds, __doc__.split("\n\n")[-1].strip())
    percents = PERCENTS[size.name]
    out["percents"] = list(percents)
    arms: dict[str, Any] = {}
    oracle: dict[str, Any] = {}
    for arm, other in ARMS.items():
        arms[arm] = {}
        for p in percents:
            protocol = MultiFreqProtocol(train_percent=p, with_other_carriers=other)
            runs = [train_and_evaluate(data, "rflscm", protocol, EXTRA[size.name], s, ctx.device) for s in seeds]
            agg = aggregate([record(r) for r in runs])
            _, train_grids, test_grids = protocol.split(data.scenario)
            arms[arm][_key(p)] = {
                "mae_db": {bt: agg["mean"]["mae_db"][bt]["all"] for bt in BEAM_TYPES},
                "mae_std_db": {bt: agg["std"]["mae_db"][bt]["all"] for bt in BEAM_TYPES},
                "train_grids": int(len(train_grids)),
                "test_grids": int(len(test_grids)),
                "trivial_mae_db": {bt: mae_summary(runs[0].metrics)["trivial"][bt]["all"] for bt in BEAM_TYPES},
                "train_time_s": agg["mean"]["train_time_s"],
            }
            oracle.setdefault(_key(p), {bt: mae_summary(runs[0].metrics)["oracle"][bt]["all"] for bt in BEAM_TYPES})
    out["carrier_hz"] = MultiFreqProtocol().carrier(data.scenario)
    out["arms"] = arms
    out["oracle_mae_db"] = oracle
    out["gain_db"], out["gain_percent"] = _gains(arms)
    out["plots"] = [_plot(ctx, percents, arms, oracle)]
    return out


def _key(p: float) -> str:
    return f"p{p:g}"


def _gains(arms: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    gain_db: dict[str, Any] = {}
    gain_pct: dict[str, Any] = {}
    for key in arms["with_other_band"]:
        gain_db[key], gain_pct[key] = {}, {}
        for bt in BEAM_TYPES:
            w, wo = arms["with_other_band"][key]["mae_db"][bt], arms["without_other_band"][key]["mae_db"][bt]
            ok = w is not None and wo is not None
            gain_db[key][bt] = wo - w if ok else None
            gain_pct[key][bt] = 100.0 * (wo - w) / wo if ok and wo > 0 else None
    return gain_db, gain_pct


def _plot(ctx: BenchContext, percents: tuple[float, ...], arms: dict[str, Any], oracle: dict[str, Any]) -> str:
    fig, axes = new_figure(ncols=2)
    for ax, bt in zip(axes, BEAM_TYPES):
        for arm, entries in arms.items():
            mae = [np.nan if e["mae_db"][bt] is None else e["mae_db"][bt] for e in entries.values()]
            ax.plot(percents, mae, marker="o", label=arm.replace("_", " "))
        ax.plot(
            percents,
            [np.nan if v[bt] is None else v[bt] for v in oracle.values()],
            color="grey",
            linestyle=":",
            label="oracle",
        )
        ax.set_xlabel("p [% of 2.1 GHz grids trained on]")
        ax.set_ylabel(f"{bt.upper()} MAE on the 2.1 GHz test grids [dB]")
        ax.legend()
    fig.suptitle("B3 multi-frequency")
    return save_figure(fig, ctx, "b3_multifreq")
