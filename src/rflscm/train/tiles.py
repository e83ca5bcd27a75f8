"""Training a tiled model (issue 29): the network cut into tiles, each tile an independent model.

:func:`fit_tiled` cuts a protocol's training scenario into tiles of about ``tile_sites`` sites
(:func:`rflscm.data.parts.plan_tiles`), fits a fresh model per tile on its part (its cells at their grids, the
other cells' reported SSB there as interference; :func:`rflscm.data.parts.tile_scenario`) with the ordinary
:func:`rflscm.train.fit`, and assembles a :class:`~rflscm.models.tiled.TiledModel`.  Each tile trains only on its
own cells, so the tiles together cost about what the whole would, but each tile's scene box, fields and data are
small.

A time budget is split so that the whole run keeps it, by each tile's training pairs (what its training and its
pass after training cost grows with): :func:`schedule` deals the tiles to the ``slots`` that run at once, largest
first to the least-loaded slot, and a tile starting on a slot gets the time left (less the share kept for writing
the checkpoint) times its pairs over the pairs of the tiles its slot has still to run, itself included
(:func:`tile_budget`).  A tile that ends early leaves its time to the next ones of its slot; no tile waits for a
slot that another queue's overrun holds.  Where the tiles run is a *runner*: :func:`serial_runner` here (one slot,
in-process), or Ray tasks (:func:`rflscm.parallel.tiles.ray_runner`).  Every tile is seeded and built
the same way wherever it runs, and comes back as its checkpoint payload, so serial and parallel runs give the
same tiles (bit-identical in step mode with one thread per worker).
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
import torch

from rflscm.config import to_dict
from rflscm.data.measurements import reported_pairs
from rflscm.data.parts import Tile, plan_tiles, tile_scenario
from rflscm.errors import ConfigError
from rflscm.geometry import AngleGrid
from rflscm.models.base import from_plain, model_from_payload, to_plain
from rflscm.train.trainer import Trainable, checked_budget, fit

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.models.tiled import TiledModel

__all__ = [
    "SAVE_SHARE",
    "TileJob",
    "TileResult",
    "TileRunner",
    "fit_tiled",
    "queue_budgets",
    "run_tile",
    "schedule",
    "serial_runner",
    "tile_budget",
]

SAVE_SHARE = 0.02
"""Share of a tiled run's budget kept after the tiles for assembling and writing the tiled checkpoint."""
CROP_MARGIN_M = 50.0
"""A tile's point cloud is cropped to the x/y box around its cells and grids grown by this much [m] (default)."""


@dataclass(frozen=True)
class TileJob:
    """Everything one tile's fit needs (plain data and a scenario part: it travels to a Ray worker)."""

    tile: Tile
    count: int
    """How many tiles the run has (for messages)."""
    scenario: Scenario
    """The tile's part of the training scenario."""
    model_name: str
    config: Any
    angle_grid: dict[str, Any]
    device: str
    seed: int
    threads: int | None
    run_info: dict[str, Any] = field(default_factory=dict)
    progress: bool = False


@dataclass
class TileResult:
    """One fitted tile: its checkpoint payload (as :meth:`LSCMModel.save` writes it) and what it cost."""

    tile: Tile
    payload: dict[str, Any]
    summary: dict[str, float]
    seconds: float
    pairs: int
    budget_s: float | None


class TileRunner(Protocol):
    """Runs the jobs ``make_job(i)`` for every tile i of ``weights`` (one per tile: its training pairs), each given
    :func:`tile_budget` of its slot's queue (:func:`schedule`) when it starts, calling ``done`` as each ends;
    returns the results in tile order."""

    def __call__(
        self,
        weights: Sequence[float],
        make_job: Callable[[int], TileJob],
        deadline: float | None,
        done: Callable[[TileResult], None],
    ) -> list[TileResult]: ...


def schedule(weights: Sequence[float], slots: int) -> list[list[int]]:
    """The tiles (indices of ``weights``) dealt to ``slots`` queues run side by side: heaviest first (ties by
    index), each to the queue with the least weight so far (ties: the first queue); each queue in the order dealt.
    Queues left empty are dropped."""
    queues: list[list[int]] = [[] for _ in range(max(1, slots))]
    load = [0.0] * len(queues)
    for i in sorted(range(len(weights)), key=lambda i: (-float(weights[i]), i)):
        q = min(range(len(queues)), key=lambda q: (load[q], q))
        queues[q].append(i)
        load[q] += max(float(weights[i]), 0.0)
    return [q for q in queues if q]


def tile_budget(deadline: float | None, weight: float, queue_weight: float, now: float | None = None) -> float | None:
    """Seconds a tile of ``weight`` starting now may take when its queue has ``queue_weight`` still to run (this
    tile included): the time to ``deadline`` (``time.time()`` clock) times ``weight / queue_weight``; at least 1 s
    (every tile needs a model, even when the time is gone); None without a deadline."""
    if deadline is None:
        return None
    left = deadline - (time.time() if now is None else now)
    share = weight / queue_weight if queue_weight > 0 else 1.0
    return max(left * min(share, 1.0), 1.0)


def queue_budgets(weights: Sequence[float], queue: Sequence[int]) -> list[tuple[float, float]]:
    """For each tile of ``queue`` (in order): its weight and the weight of the queue from it on (the arguments of
    :func:`tile_budget` when it starts)."""
    w = [max(float(weights[i]), 0.0) for i in queue]
    rest = np.cumsum(w[::-1])[::-1] if w else np.zeros(0)
    return [(w[k], float(rest[k])) for k in range(len(queue))]


def training_pairs(scenario: Scenario) -> int:
    """Distinct (cell, grid) pairs with a reported round-1 RSRP."""
    return len(reported_pairs(scenario.measurements))


def run_tile(job: TileJob, budget_s: float | None, deadline: float | None = None) -> TileResult:
    """Fit one tile: seed, build a fresh model from the job's config, :func:`rflscm.train.fit` it on the tile's part
    within ``budget_s`` (iterative models; no more than is left to ``deadline``, a ``time.time()`` value, when the
    tile starts later than planned: a task waiting for a free GPU), and return its checkpoint payload."""
    from rflscm.models import MODEL_REGISTRY

    started = time.perf_counter()
    if budget_s is not None and deadline is not None:
        budget_s = max(min(budget_s, deadline - time.time()), 1.0)
    if job.threads is not None:
        torch.set_num_threads(job.threads)
    random.seed(job.seed)
    np.random.seed(job.seed % 2**32)
    torch.manual_seed(job.seed)
    model = MODEL_REGISTRY[job.model_name].build(job.config, AngleGrid.from_dict(job.angle_grid), job.device)
    model.run_info.update(job.run_info)
    model.run_info["tile"] = {"index": job.tile.index, "sites": list(job.tile.sites), "cells": len(job.tile.cells)}
    budget = budget_s if isinstance(model, Trainable) else None
    summary = fit(model, job.scenario, progress=job.progress, budget_s=budget, started=started)
    payload = to_plain(
        {
            "model": model.name,
            "fingerprint": model.fingerprint,
            "angle_grid": model.angle_grid.to_dict(),
            "run_info": model.run_info,
            "state": model.state_dict_for_checkpoint(),
        }
    )
    return TileResult(
        job.tile,
        payload,
        {k: float(v) for k, v in summary.items()},
        time.perf_counter() - started,
        training_pairs(job.scenario),
        budget,
    )


def serial_runner(
    weights: Sequence[float],
    make_job: Callable[[int], TileJob],
    deadline: float | None,
    done: Callable[[TileResult], None],
) -> list[TileResult]:
    """The tiles one after the other (heaviest first), in this process; each gets its weight's share of the time
    left over the tiles left."""
    (queue,) = schedule(weights, 1) or [[]]
    results: dict[int, TileResult] = {}
    for i, (weight, rest) in zip(queue, queue_budgets(weights, queue), strict=True):
        job = make_job(i)
        result = run_tile(job, tile_budget(deadline, weight, rest))
        done(result)
        results[i] = result
    return [results[i] for i in range(len(weights))]


def tile_line(result: TileResult, count: int) -> str:
    """One line on a fitted tile: cells, grids, training pairs, time (and budget)."""
    t = result.tile
    line = (
        f"tile {t.index + 1}/{count}: sites {','.join(map(str, t.sites))}, {len(t.cells)} cells, {len(t.grids)} grids, "
        f"{result.pairs} training pairs, {result.seconds:.1f} s"
    )
    if result.budget_s is not None:
        line += f" of {result.budget_s:.1f} s"
    if "steps" in result.summary:
        line += f", {result.summary['steps']:.0f} steps"
    return line


def fit_tiled(
    model_name: str,
    config: Any,
    scenario: Scenario,
    protocol: Any,
    tile_sites: int,
    budget_s: float | None = None,
    started: float | None = None,
    device: torch.device | str = "cpu",
    seed: int = 0,
    angle_grid: AngleGrid | None = None,
    crop_margin_m: float | None = CROP_MARGIN_M,
    runner: TileRunner | None = None,
    report: Callable[[str], None] | None = None,
    progress: bool = True,
    run_info: dict[str, Any] | None = None,
) -> TiledModel:
    """A :class:`~rflscm.models.tiled.TiledModel` of ``model_name`` (config ``config``, as ``build`` takes it)
    fitted on ``protocol``'s training scenario of ``scenario`` in tiles of about ``tile_sites`` sites.

    ``budget_s`` (seconds of wall time from ``started``, a ``time.perf_counter()`` value, default now): the whole
    run, checkpoint writing included (:data:`SAVE_SHARE` of it is kept for that), split over the tiles as the module
    says.  ``runner``: where the tiles run (default :func:`serial_runner`); ``report`` gets one line per tile;
    ``progress``: the serial runner shows each tile's training bar.  The model's fingerprint is ``scenario``'s, its
    ``run_info`` holds the protocol, the tiling and each tile's fit.
    """
    from rflscm.models.tiled import TiledModel

    perf0 = time.perf_counter() if started is None else started
    checked_budget(budget_s)
    if tile_sites < 1:
        raise ConfigError(f"--tile-sites must be at least 1 site per tile (got {tile_sites}).")
    deadline = None
    if budget_s is not None:
        deadline = time.time() + budget_s * (1.0 - SAVE_SHARE) - (time.perf_counter() - perf0)
    training = protocol.training_scenario(scenario)
    plan = plan_tiles(training, tile_sites)
    grid = (angle_grid or AngleGrid()).to_dict()
    threads = torch.get_num_threads()
    base_info = dict(run_info or {})

    def make_job(i: int) -> TileJob:
        tile = plan[i]
        part = tile_scenario(training, tile, crop_margin_m)
        shown = progress and runner is None  # a Ray task's bar would not reach this terminal
        return TileJob(tile, len(plan), part, model_name, config, grid, str(device), seed, threads, base_info, shown)

    def done(result: TileResult) -> None:
        if report is not None:
            report(tile_line(result, len(plan)))

    weights = [float(max(t.pairs, 1)) for t in plan]
    results = (runner or serial_runner)(weights, make_job, deadline, done)
    tiles = [model_from_payload(from_plain(r.payload), device) for r in sorted(results, key=lambda r: r.tile.index)]
    tiled = TiledModel.from_tiles(tiles, plan, scenario.grids, device)
    tiled.fingerprint = scenario.fingerprint()
    tiled.run_info.update(base_info)
    tiled.run_info["protocol"] = to_dict(protocol)  # as rflscm.eval.protocols.protocol_to_dict writes it
    tiled.run_info["tiling"] = {
        "tile_sites": tile_sites,
        "tiles": len(plan),
        "crop_margin_m": crop_margin_m,
        "model": model_name,
    }
    per_tile = [{"seconds": r.seconds, "pairs": r.pairs, **r.summary} for r in results]
    tiled.run_info["fit"] = {
        "train_time_s": time.perf_counter() - perf0,
        "tiles": float(len(plan)),
        "tile_seconds": float(sum(r.seconds for r in results)),
        **({"budget_s": float(budget_s)} if budget_s is not None else {}),
    }
    tiled.run_info["tile_fits"] = per_tile
    return tiled
