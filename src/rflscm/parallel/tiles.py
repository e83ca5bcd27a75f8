"""Tiles trained as Ray tasks (issue 29): the runner :func:`ray_runner` for :func:`rflscm.train.tiles.fit_tiled`.

At most ``engine.workers`` tiles run at once, each a Ray task of one CPU (and one GPU, ``num_gpus=1``, when the
tiles train on CUDA).  The tiles are dealt to that many queues by their training pairs
(:func:`rflscm.train.tiles.schedule`); when a queue's task ends, its next tile starts with its share of the time
left (:func:`rflscm.train.tiles.tile_budget`), so the run keeps its budget and no tile waits for another queue.
A task runs exactly what the serial runner runs in-process (:func:`rflscm.train.tiles.run_tile`: seeded, built and
fitted the same way, with the driver's torch thread count) and returns the tile's checkpoint payload, so the tiled
model is the serial one (bit-identical in step mode with ``--threads 1``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from tqdm.auto import tqdm

from rflscm.errors import RflscmError
from rflscm.parallel.engine import Engine, ray_session
from rflscm.train.tiles import TileJob, TileResult, TileRunner, queue_budgets, run_tile, schedule, tile_budget

__all__ = ["ray_runner"]


def ray_runner(engine: Engine, gpus: bool = False) -> TileRunner:
    """A tile runner on Ray (local, started on demand, or the cluster at ``engine.address``): ``engine.workers``
    tiles at once; ``gpus``: each task asks Ray for one GPU (the tiles train on CUDA)."""

    def run(
        weights: Sequence[float],
        make_job: Callable[[int], TileJob],
        deadline: float | None,
        done: Callable[[TileResult], None],
    ) -> list[TileResult]:
        with ray_session(engine) as ray:
            task = ray.remote(num_cpus=1, num_gpus=1 if gpus else 0, max_retries=0)(run_tile)
            slots = max(1, engine.workers)
            if gpus:  # no more tiles at once than GPUs: a task waiting for one would start late
                slots = max(1, min(slots, int(ray.cluster_resources().get("GPU", 0)) or slots))
            queues = [list(zip(q, queue_budgets(weights, q), strict=True)) for q in schedule(weights, slots)]
            pending: dict[Any, tuple[int, int]] = {}  # task → (queue, tile)
            results: dict[int, TileResult] = {}

            def start(q: int) -> None:
                if queues[q]:
                    index, (weight, rest) = queues[q].pop(0)
                    budget = tile_budget(deadline, weight, rest)
                    pending[task.remote(make_job(index), budget, deadline)] = (q, index)

            bar = tqdm(total=len(weights), desc=f"tiles on {len(queues)} Ray workers", unit="tile", disable=None)
            try:
                for q in range(len(queues)):
                    start(q)
                while pending:
                    ready, _ = ray.wait(list(pending), num_returns=1)
                    for ref in ready:
                        q, index = pending.pop(ref)
                        results[index] = ray.get(ref)
                        done(results[index])
                        bar.update(1)
                        start(q)
            except ray.exceptions.RayError as exc:
                cause = getattr(exc, "cause", None)
                if isinstance(cause, RflscmError):
                    raise cause from None
                raise RflscmError(f"a Ray worker failed training a tile: {str(exc).strip().splitlines()[-1]}") from None
            finally:
                bar.close()
            return [results[i] for i in range(len(weights))]

    return run
