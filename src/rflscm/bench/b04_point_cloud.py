"""B4 — point-cloud prior on/off with 10 % of the training grids (paper §VI-C).

RF-LSCM is trained on the round-1 measurements of a seeded 10 % of the benchmark scenario's
measured grids, with the point-cloud prior Φ (default) and without it (``prior.enabled: false``:
Φ = 1 everywhere, so no sample is skipped either), and tested on round 2 at every grid (the adjust
protocol; 90 % of the test grids are unseen in training).  Reported: MAE [dB] (SSB, CSI-RS; all and
changed cells), the MAE against the noiseless truth over every beam above r_th (``truth_mae_db``), the
MAE on the unseen grids, the oracle, training time; plots: the MAEs and the
attenuation maps (paper Fig. "deltahanghzou"): the largest per-voxel loss Φ·loss_dB at the
reference carrier over height, top-down, with and without the prior.

Seeds: seed ``s`` draws the 10 % of grids (``split_grids(…, s)``) and initialises both arms; ``--seeds N``
averages over N draws (with 15 training grids the draw decides more than the initialisation).

Sizes: ``quick`` = the B1 quick scenario (one site, 150 grids → 15 training grids), 200 steps of 8
pairs (HiTAM warm-up 80, ramp 20): without the prior every one of the Q samples of a ray is
rendered (~10× the cost of a step and of the evaluation), 2 CPU cores; ``full`` = the whole
scenario and the ``full`` preset.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from rflscm.bench import BenchContext, register_bench
from rflscm.bench.harness import (
    BenchSize,
    bench_size,
    field_model,
    load_bench_data,
    merge,
    restrict_round1,
    train_and_evaluate,
)
from rflscm.bench.report import aggregate, header, mae_summary, new_figure, record, save_figure, seeds_of
from rflscm.data import BEAM_TYPES
from rflscm.eval import AdjustProtocol

if TYPE_CHECKING:
    from rflscm.models.rflscm import RFLSCM

TRAIN_FRACTION = 0.1
VARIANTS = {"prior_on": {}, "prior_off": {"prior": {"enabled": False}}}
EXTRA = {
    "tiny": {},
    "quick": {"train": {"steps": 200, "batch_pairs": 8}, "hitam": {"warmup_steps": 80, "ramp_steps": 20}},
    "full": {},
}


@register_bench("b4", "point-cloud prior on/off, RF-LSCM trained on 10 % of the grids")
def run(ctx: BenchContext) -> dict[str, Any]:
    return run_b4(ctx, bench_size(ctx.size))


def run_b4(ctx: BenchContext, size: BenchSize, extra: dict[str, Any] | None = None) -> dict[str, Any]:
    """B4 at ``size``; ``extra``: overrides for both arms on top of the size's (probes:
    ``experiments/b4_probe.py``).  Seed ``s`` draws the training grids and initialises both arms, so the arms
    of one seed see the same grids and ``prior_gain_db`` is the mean of paired differences."""
    full = load_bench_data(ctx, size)
    seeds = seeds_of(ctx)
    draws = {s: restrict_round1(full, TRAIN_FRACTION, seed=s) for s in seeds}
    out = header(ctx, draws[seeds[0]][0], seeds, "\n\n".join(__doc__.split("\n\n")[-2:]).strip())
    out["train_fraction"] = TRAIN_FRACTION
    out["train_grids"] = int(len(draws[seeds[0]][1]))
    out["train_grid_ids"] = {str(s): sorted(int(g) for g in draws[s][1]) for s in seeds}
    out["extra"] = extra or {}
    variants: dict[str, Any] = {}
    maps: dict[str, np.ndarray] = {}
    references: list[dict[str, Any]] = []
    records: dict[str, list[dict[str, Any]]] = {}
    for key, arm in VARIANTS.items():
        over = merge(merge(EXTRA[size.name], extra or {}), arm)
        runs = [train_and_evaluate(draws[s][0], "rflscm", AdjustProtocol(), over, s, ctx.device) for s in seeds]
        records[key] = [record(r) for r in runs]
        agg = aggregate(records[key])
        variants[key] = {
            "mae_db": agg["mean"]["mae_db"],
            "mae_std_db": agg["std"]["mae_db"],
            "truth_mae_db": agg["mean"]["truth_mae_db"],
            "unseen_mae_db": agg["mean"]["unseen_mae_db"],
            "unseen_bias_db": agg["mean"]["unseen_bias_db"],
            "train_time_s": agg["mean"]["train_time_s"],
            "peak_memory_mb": agg["mean"]["peak_memory_mb"],
        }
        references = references or [mae_summary(r.metrics) for r in runs]
        maps[key] = attenuation_map(field_model(runs[0].model))
    out["variants"] = variants
    reference = aggregate(references)["mean"]
    out["oracle"] = {"mae_db": reference["oracle"], "truth_mae_db": reference["truth"]["oracle"]}
    out["trivial"] = {"mae_db": reference["trivial"], "truth_mae_db": reference["truth"]["trivial"]}
    gains = [
        {bt: _diff(off["mae_db"][bt]["all"], on["mae_db"][bt]["all"]) for bt in BEAM_TYPES}
        for on, off in zip(records["prior_on"], records["prior_off"], strict=True)
    ]
    spread = aggregate(gains)
    out["prior_gain_per_seed_db"], out["prior_gain_db"], out["prior_gain_std_db"] = gains, spread["mean"], spread["std"]
    out["plots"] = [_plot_mae(ctx, variants), _plot_maps(ctx, maps, field_model(runs[0].model))]
    return out


def _diff(a: float | None, b: float | None) -> float | None:
    return None if a is None or b is None else a - b


@torch.no_grad()
def attenuation_map(model: RFLSCM, resolution_m: float = 4.0, heights: int = 12) -> np.ndarray:
    """Top-down map ``[ny, nx]`` of the largest per-voxel loss [dB] at the reference carrier over height,
    Φ-weighted as rendered (δ̃ = δ^Φ), of the refinement (else only) stage of a field model."""
    if model.scene is None:
        raise ValueError("the field model has no scene (it was never trained)")
    frame = model.scene.frame
    lo, hi = np.asarray(frame.box_lo), np.asarray(frame.box_hi)
    xs = np.arange(lo[0], hi[0], resolution_m)
    ys = np.arange(lo[1], hi[1], resolution_m)
    zs = np.linspace(max(lo[2], 0.0), hi[2], heights)
    pts = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), -1).reshape(-1, 3)
    points = torch.as_tensor(pts, dtype=torch.float32, device=model.device)
    stage: Any = model.stages["fine"]  # a RadianceStage; an nn.ModuleDict's items are typed nn.Module
    loss = stage.medium.loss_db(stage.fields.delta(stage.fields.encode(points)))
    if model.prior is not None:
        loss = loss * model.prior(points)
    return loss.view(len(xs), len(ys), len(zs)).amax(-1).T.cpu().numpy()


def _plot_mae(ctx: BenchContext, variants: dict[str, Any]) -> str:
    fig, (ax,) = new_figure()
    groups = [("ssb", "all"), ("ssb", "changed"), ("csi", "all"), ("csi", "changed")]
    x = np.arange(len(groups))
    for i, (key, v) in enumerate(variants.items()):
        vals = [v["mae_db"][bt][w] for bt, w in groups]
        ax.bar(x + 0.4 * i, [np.nan if a is None else a for a in vals], 0.4, label=key.replace("_", " "))
    ax.set_xticks(x + 0.2, [f"{bt.upper()} {w}" for bt, w in groups])
    ax.set_ylabel("MAE after adjustment [dB]")
    ax.set_title(f"B4 point-cloud prior ({int(100 * TRAIN_FRACTION)} % of grids)")
    ax.legend()
    return save_figure(fig, ctx, "b4_mae")


def _plot_maps(ctx: BenchContext, maps: dict[str, np.ndarray], model: RFLSCM) -> str:
    fig, axes = new_figure(ncols=len(maps))
    if model.scene is None:
        raise ValueError("the field model has no scene (it was never trained)")
    frame = model.scene.frame
    extent = (frame.box_lo[0], frame.box_hi[0], frame.box_lo[1], frame.box_hi[1])
    for ax, (key, m) in zip(axes, maps.items()):
        im = ax.imshow(m, origin="lower", extent=extent, cmap="magma")
        ax.set_title(f"{key.replace('_', ' ')}: max loss per voxel [dB]")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        fig.colorbar(im, ax=ax, shrink=0.8)
    return save_figure(fig, ctx, "b4_attenuation")
