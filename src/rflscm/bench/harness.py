"""Shared machinery of the paper benchmarks B1–B6: sizes, the benchmark scenario, and "train model X with
overrides under protocol P and evaluate" (:func:`train_and_evaluate`).  Memory and throughput probes
live in :mod:`rflscm.bench.measure`, records, seeds and figures in :mod:`rflscm.bench.report`.

A :class:`BenchSize` fixes everything a size means: which part of the scenario is used (sites,
grids, a cropped point cloud), the angle grid, and per-model config overrides laid over the
model's preset of the same name (``quick``/``full``; the dataclass defaults where a preset file is
absent).  The CLI only knows ``quick`` and ``full`` (:func:`bench_size`); tests pass
:func:`tiny_size` to a benchmark's ``run_*`` function directly.
"""

from __future__ import annotations

import copy
import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import torch

from rflscm.bench import BenchContext
from rflscm.bench.measure import MemoryProbe
from rflscm.config import load_yaml, to_dict
from rflscm.data.measurements import reported_pairs
from rflscm.data.parts import scenario_part
from rflscm.errors import ConfigError
from rflscm.geometry import AngleGrid

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.eval.cache import APSCache
    from rflscm.eval.protocols import Protocol
    from rflscm.models.base import LSCMModel
    from rflscm.models.rflscm import RFLSCM
    from rflscm.models.source import APSSource
    from rflscm.models.wnomp import WNOMPModel

FIELD_MODELS = ("rflscm", "nerf2")


# --- sizes -----------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BenchSize:
    """What a benchmark size means (recorded verbatim in every benchmark's JSON under ``size``)."""

    name: str
    max_sites: int | None
    """Sites kept (all their cells, every carrier), ranked by changed cells with round-1 reports, then by
    reported pairs, then by id; None = all."""
    max_grids: int | None
    """Grids kept: those with round-1 data from the kept cells nearest to a kept site; None = all."""
    crop_margin_m: float | None
    """The point cloud is cropped to the box around kept cells and grids grown by this [m]; None = not cropped."""
    angle_grid: tuple[int, int, float, float]
    """(num_el, num_az, el_min_deg, el_step_deg) of the models' and the oracle's angle grid."""
    overrides: dict[str, dict[str, Any]] = field(default_factory=dict)
    """Model name → nested config overrides laid over the model's preset ``name``."""
    preset: str = "quick"
    """Model preset the overrides are laid over (``quick`` or ``full``)."""

    def grid(self) -> AngleGrid:
        return AngleGrid(*self.angle_grid)

    def describe(self) -> dict[str, Any]:
        return to_dict(self)


def _train(steps: int, batch: int, val_every: int, val_pairs: int = 64) -> dict[str, Any]:
    return {
        "steps": steps,
        "batch_pairs": batch,
        "val_every": val_every,
        "val_pairs": val_pairs,
        "checkpoint_every": 10**6,
    }


def quick_size() -> BenchSize:
    """2 CPU cores, at most fifteen minutes per benchmark: one site (its 6 cells on both carriers), the 150
    measured grids nearest to it, the paper's 91 × 72 angle grid, the models' ``quick`` presets with
    1500 training steps of 32 pairs (HiTAM warm-up 600, ramp 150), validation only at the end; NeRF²
    at its quick preset's shrunk widths.  Benchmarks with many runs cut the steps further (their
    ``EXTRA``).  Far from converged: quick checks that the machinery runs and shows trends; the
    paper-like numbers need ``full``."""
    hitam = {"warmup_steps": 600, "ramp_steps": 150}
    train = _train(1500, 32, 1500, val_pairs=64)
    return BenchSize(
        name="quick",
        max_sites=1,
        max_grids=150,
        crop_margin_m=20.0,
        angle_grid=(91, 72, -90.0, 2.0),
        overrides={"rflscm": {"train": train, "hitam": hitam}, "nerf2": {"train": train, "hitam": hitam}, "wnomp": {}},
        preset="quick",
    )


def full_size() -> BenchSize:
    """The paper-like setting for a GPU: the whole scenario and the models' ``full`` presets unchanged."""
    return BenchSize(
        name="full",
        max_sites=None,
        max_grids=None,
        crop_margin_m=None,
        angle_grid=(91, 72, -90.0, 2.0),
        overrides={"rflscm": {}, "nerf2": {}, "wnomp": {}},
        preset="full",
    )


def tiny_size() -> BenchSize:
    """Plumbing tests only (seconds): a coarse 16 × 18 angle grid, narrow networks, a handful of steps."""
    hitam = {"beta": 2, "top_k": 4, "warmup_steps": 3, "ramp_steps": 2}
    train = _train(6, 8, 3, val_pairs=8)
    return BenchSize(
        name="tiny",
        max_sites=1,
        max_grids=24,
        crop_margin_m=10.0,
        angle_grid=(16, 18, -90.0, 12.0),
        overrides={
            "rflscm": {
                "train": train,
                "hitam": hitam,
                "decoder": {"hidden": 16},
                "field": {"voxel_m": 16.0, "delta_rank": 2, "feature_rank": 2, "feature_dim": 4},
            },
            "nerf2": {
                "train": train,
                "hitam": hitam,
                "decoder": {"hidden": 16, "head_hidden": 8},
                "field": {"hidden": 16, "layers": 4, "skip_at": 2, "pos_freqs": 4, "feature_dim": 8},
            },
            "wnomp": {"k_max": 4},
        },
        preset="quick",
    )


def bench_size(name: str) -> BenchSize:
    """The size behind ``rflscm bench --size`` (``quick`` or ``full``)."""
    sizes = {"quick": quick_size, "full": full_size}
    if name not in sizes:
        raise ConfigError(f"benchmark size must be one of {', '.join(sizes)} (got {name!r}).")
    return sizes[name]()


def merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """Recursive dict merge (``over`` wins; nested mappings merge, except learning-rate dicts)."""
    out = copy.deepcopy(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict) and key != "lr":
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def model_config(
    model: str, size: BenchSize, extra: dict[str, Any] | None = None, seed: int | None = None
) -> dict[str, Any]:
    """The config mapping of ``model`` at ``size``: preset YAML (if shipped) ← size overrides ← ``extra``
    ← ``train.seed``."""
    from rflscm.models.rflscm.config import preset_path

    base: dict[str, Any] = {}
    if model in FIELD_MODELS and preset_path(size.preset, model).is_file():
        base = load_yaml(preset_path(size.preset, model))
    cfg = merge(merge(base, size.overrides.get(model, {})), extra or {})
    if seed is not None and model in FIELD_MODELS:
        cfg = merge(cfg, {"train": {"seed": int(seed)}})
    return cfg


# --- the benchmark scenario ---------------------------------------------------------------------------
@dataclass
class BenchData:
    """The full scenario, the benchmark's sub-scenario of it, and the oracle fitted on the sub-scenario."""

    full: Scenario
    scenario: Scenario
    oracle: APSSource | None
    size: BenchSize
    info: dict[str, Any]


def scenario_path(ctx: BenchContext) -> tuple[Path, str]:
    """``(folder, source)``: ``--scenario``, else the shipped default, else a procedural scenario made once
    with ``rflscm simulate``'s defaults into ``<out>/_default_scenario``."""
    if ctx.scenario:
        return Path(ctx.scenario), "--scenario"
    from rflscm.sim import default_scenario_path

    shipped = default_scenario_path()
    if (shipped / "scenario.yaml").is_file():
        return shipped, "shipped default"
    made = Path(ctx.out_dir) / "_default_scenario"
    if not (made / "scenario.yaml").is_file():
        from rflscm.sim import SimulationConfig, build_scenario, make_backend

        cfg = SimulationConfig(name="bench-default")
        build_scenario(make_backend("procedural", "city", seed=cfg.seed), cfg, made, progress=False, scene="city")
    return made, "generated: procedural city, SimulationConfig defaults (seed 0), no default scenario is shipped"


def load_bench_data(ctx: BenchContext, size: BenchSize) -> BenchData:
    """Load the scenario, cut the sub-scenario of ``size`` and fit the oracle (when truth exists)."""
    from rflscm.data import load_scenario

    path, source = scenario_path(ctx)
    full = load_scenario(path)
    sub, info = sub_scenario(full, size)
    oracle = None
    if full.meta.truth is not None:
        from rflscm.eval.oracle import OracleModel

        oracle = OracleModel.for_scenario(sub, size.grid(), ctx.device)
    info.update(scenario=str(path), source=source, name=full.meta.name, oracle=oracle is not None)
    return BenchData(full, sub, oracle, size, info)


def restrict_round1(data: BenchData, fraction: float, seed: int = 0) -> tuple[BenchData, np.ndarray]:
    """``data`` whose round-1 measurements keep only a seeded ``fraction`` of the measured grids (round 2
    untouched, so the adjust protocol trains on that fraction and tests on every grid); and those grids."""
    from rflscm.eval import split_grids

    keep = split_grids(data.scenario, fraction, seed)
    m = data.scenario.measurements
    rows = (m["round"] != 1).to_numpy() | m["grid_id"].isin(keep).to_numpy()
    scenario = data.scenario.with_measurements(m[rows], validate=False)
    return dataclasses.replace(data, scenario=scenario), keep


def _site_order(full: Scenario) -> list[int]:
    """Sites with reported round-1 data, ranked by changed cells that have such data, then by reported
    (cell, grid) pairs, then by id (a ray-traced scene can leave whole sites without any report)."""
    cells = full.cells[1]
    changed: set[int] = set()
    if 2 in full.cells:
        from rflscm.eval.metrics import changed_cells

        changed = set(changed_cells(full, 1, 2).tolist())
    pairs_per_cell = reported_pairs(full.measurements).groupby("cell_id").size()
    rank = []
    for site, group in cells.groupby("site_id"):
        counts = pairs_per_cell.reindex(group["cell_id"]).fillna(0).to_numpy()
        if counts.sum() == 0:
            continue
        n_changed = int(sum(c in changed and n > 0 for c, n in zip(group["cell_id"], counts)))
        rank.append((-n_changed, -int(counts.sum()), int(site)))
    return [site for *_, site in sorted(rank)]


def sub_scenario(full: Scenario, size: BenchSize) -> tuple[Scenario, dict[str, Any]]:
    """The part of ``full`` a size uses (deterministic; see :class:`BenchSize`) and a description."""
    cells1 = full.cells[1]
    sites = _site_order(full)[: size.max_sites] if size.max_sites else sorted(cells1["site_id"].unique().tolist())
    keep_cells = np.sort(cells1.loc[cells1["site_id"].isin(sites), "cell_id"].to_numpy(np.int64))
    m = full.measurements
    m = m[m["cell_id"].isin(keep_cells).to_numpy()]
    r1 = m[(m["round"] == 1).to_numpy() & m["rsrp_dbm"].notna().to_numpy()]
    grids = full.grids[full.grids["grid_id"].isin(r1["grid_id"].unique())]
    if size.max_grids and len(grids) > size.max_grids:
        site_xy = cells1.loc[cells1["cell_id"].isin(keep_cells), ["x", "y"]].drop_duplicates().to_numpy()
        d = np.linalg.norm(grids[["x", "y"]].to_numpy()[:, None, :] - site_xy[None], axis=-1).min(1)
        order = np.lexsort((grids["grid_id"].to_numpy(), d))
        grids = grids.iloc[np.sort(order[: size.max_grids])]
    sub = scenario_part(full, keep_cells, grids["grid_id"].to_numpy(), size.crop_margin_m)
    cloud, m = sub.point_cloud, sub.measurements
    info = {
        "sites": [int(s) for s in sites],
        "cells": keep_cells.tolist(),
        "grids": int(len(grids)),
        "measurement_rows": int(len(m)),
        "point_cloud_points": 0 if cloud is None else int(len(cloud.xyz)),
        "full_cells": int(len(cells1)),
        "full_grids": int(len(full.grids)),
    }
    return sub, info


# --- one run -------------------------------------------------------------------------------------------
@dataclass
class RunResult:
    """One model trained under one protocol and evaluated."""

    model: LSCMModel
    metrics: dict[str, Any]
    fit: dict[str, float]
    train_time_s: float
    memory: dict[str, float | None]
    history: list[dict[str, float]]
    config: dict[str, Any]
    judged: APSCache
    """The model as evaluation saw it: an :class:`~rflscm.eval.cache.APSCache` holding the rendered test APS."""


def build_model(
    data: BenchData, name: str, extra: dict[str, Any] | None = None, seed: int = 0, device: str = "cpu"
) -> LSCMModel:
    """A fresh model ``name`` at the benchmark's size with ``extra`` overrides."""
    from rflscm.models import MODEL_REGISTRY

    cfg = model_config(name, data.size, extra, seed)
    model = MODEL_REGISTRY[name].build(cfg, data.size.grid(), device)
    model.run_info["bench_config"] = cfg
    return model


def train_and_evaluate(
    data: BenchData,
    name: str,
    protocol: Protocol | None = None,
    extra: dict[str, Any] | None = None,
    seed: int = 0,
    device: str = "cpu",
    on_step: Callable[[LSCMModel, dict[str, float]], None] | None = None,
    evaluate_model: bool = True,
    time_budget_s: float | None = None,
    select_wnomp: bool = True,
) -> RunResult:
    """Train model ``name`` (size overrides ← ``extra``, ``train.seed`` = ``seed``) on ``protocol``'s training
    data of the benchmark scenario and evaluate it (oracle next to it).

    ``on_step(model, metrics)`` is called after every training step of a field model; its own run
    time is *not* counted in ``time_s``.  ``time_budget_s`` stops training after the first step past
    that much training time (the trainer has no such option, so the callback raises
    :class:`_StopTraining`; the model keeps the weights of the last completed step).
    ``select_wnomp`` (WNOMP only): choose its settings on held-aside beams of the protocol's training data
    (:func:`selected_wnomp`), as ``rflscm demo`` does; False keeps the size's (default) settings.
    """
    from rflscm.eval import AdjustProtocol, fit_with_protocol, run_evaluation
    from rflscm.eval.cache import APSCache

    protocol = protocol or AdjustProtocol()
    torch.manual_seed(seed)
    model = build_model(data, name, extra, seed, device)
    if name == "wnomp" and select_wnomp:
        model = selected_wnomp(model, protocol.training_scenario(data.scenario), seed, device)
    history: list[dict[str, float]] = []
    excluded = [0.0]

    def callback(metrics: dict[str, float]) -> None:
        t0 = time.perf_counter()
        row = dict(metrics)
        if "time_s" in row:
            row["time_s"] = row["time_s"] - excluded[0]
        if on_step is not None:
            on_step(model, row)
        history.append(row)
        excluded[0] += time.perf_counter() - t0
        if time_budget_s is not None and row.get("time_s", 0.0) >= time_budget_s:
            raise _StopTraining

    with MemoryProbe(device) as mem:
        t0 = time.perf_counter()
        try:
            summary = fit_with_protocol(model, data.scenario, protocol, progress=False, callback=callback)
        except _StopTraining:
            last = history[-1]
            summary = {
                "train_time_s": last["time_s"],
                "steps": last["step"],
                "final_loss": last["total"],
                "val_mae_db": last["val_mae_db"],
                "stopped_by_time_budget": 1.0,
            }
        wall = time.perf_counter() - t0 - excluded[0]
    model.run_info["fit"] = {k: float(v) for k, v in summary.items()}
    metrics = {}
    judged = APSCache(model)
    if evaluate_model:
        metrics = run_evaluation(judged, data.scenario, protocol, oracle=data.oracle).metrics
    return RunResult(
        model,
        metrics,
        {k: float(v) for k, v in summary.items()},
        wall,
        mem.result(),
        history,
        model.run_info["bench_config"],
        judged,
    )


def selected_wnomp(model: LSCMModel, training: Scenario, seed: int, device: str) -> LSCMModel:
    """A WNOMP model whose settings were chosen on held-aside round-1 beams of ``training`` (the protocol's
    training data: never round 2, never the held-out grids), starting from ``model``'s configuration; the
    choice, every candidate's held-aside MAE and the time taken go to ``run_info["wnomp_selection"]``."""
    from rflscm.models.wnomp import WNOMPModel
    from rflscm.models.wnomp_select import select_wnomp

    t0 = time.perf_counter()
    base = cast("WNOMPModel", model).config
    chosen, table = select_wnomp(training, model.angle_grid, seed=seed, device=device, base=base)
    out = WNOMPModel(chosen, model.angle_grid, device)
    out.run_info = dict(model.run_info)
    out.run_info["bench_config"] = dataclasses.asdict(chosen)
    out.run_info["wnomp_selection"] = {
        "chosen": dataclasses.asdict(chosen),
        "time_s": time.perf_counter() - t0,
        "candidates": table.to_dict(orient="records"),
    }
    return out


def field_model(model: LSCMModel) -> RFLSCM:
    """``model`` as the field model (RF-LSCM or NeRF²-LSCM) a benchmark probes inside (fields, validation MAE)."""
    from rflscm.models.rflscm import RFLSCM

    if not isinstance(model, RFLSCM):
        raise TypeError(f"a field model (rflscm, nerf2) was expected, not {model.name}")
    return model


class _StopTraining(Exception):
    """Raised from the training callback when a run's time budget is spent."""
