"""Reporting helpers of the benchmarks: the common JSON head, seeds, per-run records and their mean ± std
over seeds, and figures."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from rflscm.bench import BenchContext
from rflscm.data import BEAM_TYPES

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from rflscm.bench.harness import BenchData, RunResult


def record(result: RunResult) -> dict[str, Any]:
    """The numbers of one run a benchmark reports (stable keys; ``None`` where they do not apply)."""
    m = result.metrics
    unseen = (m.get("unseen") or {}).get("mae_db") or {}
    aps = m.get("aps") or {}
    return {
        "mae_db": mae_summary(m)["model"] if m else None,
        "seen_mae_db": mae_summary(m.get("seen") or {})["model"] if m else None,
        "truth_mae_db": truth_summary(m)["model"] if m else None,
        "unseen_mae_db": {bt: unseen.get(bt) for bt in BEAM_TYPES},
        "unseen_bias_db": {bt: ((m.get("unseen") or {}).get("bias_db") or {}).get(bt) for bt in BEAM_TYPES},
        "aps_nmse_db": aps.get("nmse_db"),
        "aps_angle_error_deg": aps.get("angle_error_deg"),
        "train_time_s": result.train_time_s,
        "steps": result.fit.get("steps"),
        "val_mae_db": result.fit.get("val_mae_db"),
        "peak_memory_mb": result.memory["peak_mb"],
        "memory_increase_mb": result.memory["increase_mb"],
    }


def aggregate(records: list[Any]) -> Any:
    """Mean and std over seeds of every numeric leaf: ``{"mean": tree, "std": tree}`` (same tree shape)."""
    first = records[0]
    if isinstance(first, dict):
        parts = {k: aggregate([r[k] if r is not None else None for r in records]) for k in first}
        return {"mean": {k: v["mean"] for k, v in parts.items()}, "std": {k: v["std"] for k, v in parts.items()}}
    values = [r for r in records if isinstance(r, (int, float)) and not isinstance(r, bool)]
    if len(values) != len(records) and not values:
        return {"mean": first if not isinstance(first, (int, float)) else None, "std": None}
    stats = mean_std(values)
    return {"mean": stats["mean"], "std": stats["std"]}


def mae_summary(metrics: dict[str, Any]) -> dict[str, Any]:
    """The MAE block a benchmark table shows: model / oracle / trivial × {ssb, csi} × {all, changed} [dB], and
    ``truth``: the same three against the noiseless truth (:func:`truth_summary`)."""
    out: dict[str, Any] = {}
    for who, key in (("model", "mae_db"), ("oracle", "oracle_mae_db"), ("trivial", "trivial_mae_db")):
        block = metrics.get(key) or {}
        out[who] = {bt: dict(block.get(bt) or {"all": None, "changed": None}) for bt in BEAM_TYPES}
    out["truth"] = truth_summary(metrics)
    return out


def truth_summary(metrics: dict[str, Any]) -> dict[str, Any]:
    """``truth_mae_db`` (every beam ≥ r_th against the noiseless truth): model / oracle / trivial × {ssb, csi} ×
    {all, changed} [dB], ``None`` leaves without ground truth."""
    block = metrics.get("truth_mae_db") or {}
    return {
        who: {bt: dict((block.get(who) or {}).get(bt) or {"all": None, "changed": None}) for bt in BEAM_TYPES}
        for who in ("model", "oracle", "trivial")
    }


# --- reporting -----------------------------------------------------------------------------------------
def header(ctx: BenchContext, data: BenchData, seeds: list[int], notes: str) -> dict[str, Any]:
    """The common head of every benchmark's result: size, scenario, seeds, what the size means."""
    return {"size": data.size.describe(), "scenario": data.info, "seeds": seeds, "notes": notes}


def seeds_of(ctx: BenchContext) -> list[int]:
    """``ctx.seeds`` consecutive seeds from the CLI's ``--seed`` (``torch.initial_seed()`` after seeding)."""
    base = int(torch.initial_seed()) % 2**31
    return [base + i for i in range(ctx.seeds)]


def save_figure(fig: Figure, ctx: BenchContext, name: str) -> str:
    """Write ``fig`` as ``<out>/<name>.png`` and close it; returns the file name."""
    import matplotlib.pyplot as plt

    path = Path(ctx.out_dir) / f"{name}.png"
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
    return path.name


def new_figure(ncols: int = 1, width: float = 5.5) -> tuple[Any, Any]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, ncols, figsize=(width * ncols, 4.0), squeeze=False)
    return fig, axes[0]


def mean_std(values: Sequence[float | None]) -> dict[str, float | None]:
    """Mean and (population) standard deviation of the finite values, ``None`` when there are none."""
    arr = np.asarray([v for v in values if v is not None and np.isfinite(v)], dtype=np.float64)
    if arr.size == 0:
        return {"mean": None, "std": None, "n": 0}
    return {"mean": float(arr.mean()), "std": float(arr.std()), "n": int(arr.size)}
