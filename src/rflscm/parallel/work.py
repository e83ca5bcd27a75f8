"""An ordered map over Ray workers: the jobs of a loop the serial code runs with ``map`` (issue 29).

:func:`mapper` gives, for an :class:`~rflscm.parallel.engine.Engine`, a callable with the signature of the
built-in ``map`` (``mapper(fn, jobs)`` → an iterator of ``fn(job)`` in the jobs' order): ``map`` itself for one
worker, else one that sends the jobs to Ray actors.  Each actor receives ``fn`` once (a module-level function or a
``functools.partial`` of one, so that it pickles), takes the driver's torch thread count (one thread per worker
gives the serial numbers to the bit), and runs the jobs it is given in turn.  At most ``window`` jobs are out at a
time and the jobs are drawn from their iterator only as results are taken, so a job that carries data (one site's
paths) costs memory only while it is out; a result that arrives early waits for the ones before it.

``rflscm simulate`` traces one (site, carrier) per job and computes one (site, carrier, round)'s noiseless RSRP per
job this way (:func:`rflscm.sim.builder.trace_all`, :func:`rflscm.sim.stream.stream_ideal`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from itertools import islice
from typing import Any

import torch

from rflscm.errors import ConfigError, RflscmError
from rflscm.parallel.engine import Engine, ray_session
from rflscm.runtime import Mapper

JOBS_PER_WORKER = 2  # out at once per worker: one running, one queued behind it


class _Worker:
    """A Ray actor that runs ``fn`` on the jobs it is sent."""

    def __init__(self, fn: Callable[[Any], Any], threads: int) -> None:
        torch.set_num_threads(threads)
        self.fn = fn

    def run(self, job: Any) -> Any:
        return self.fn(job)


@contextmanager
def mapper(engine: Engine, what: str = "a job", gpus: bool = False) -> Iterator[Mapper]:
    """``map`` for one worker in-process; else an ordered map over ``engine.workers`` Ray actors (a local Ray
    started on demand, or the cluster at ``engine.address``), each asking for one CPU (and one GPU with ``gpus``:
    then no more actors than the cluster's GPUs, and a cluster without one is a :class:`ConfigError`).
    ``what`` names a job in the error raised when a worker fails (e.g. ``"a trace"``)."""
    if not engine.parallel:
        yield map
        return
    with ray_session(engine) as ray:
        from ray.util import ActorPool

        actor = ray.remote(num_cpus=1, num_gpus=1 if gpus else 0, max_restarts=0)(_Worker)
        threads = torch.get_num_threads()
        workers = engine.workers
        if gpus:  # an actor holds its GPU for life: no more actors than GPUs, or the extra ones never start
            available = int(ray.cluster_resources().get("GPU", 0))
            if available == 0:
                raise ConfigError("the Ray cluster has no GPU for CUDA workers; pass --device cpu.")
            workers = min(workers, available)

        def ordered(fn: Callable[[Any], Any], jobs: Iterable[Any]) -> Iterator[Any]:
            actors = [actor.remote(fn, threads) for _ in range(workers)]
            pool = ActorPool(actors)
            todo = iter(jobs)

            def submit(job: Any) -> None:
                pool.submit(lambda a, j: a.run.remote(j), job)

            try:
                for job in islice(todo, JOBS_PER_WORKER * workers):
                    submit(job)
                while pool.has_next():
                    try:
                        result = pool.get_next()
                    except ray.exceptions.RayError as exc:
                        cause = getattr(exc, "cause", None)
                        if isinstance(cause, RflscmError):
                            raise cause from None
                        last = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
                        raise RflscmError(f"a Ray worker failed on {what}: {last}") from None
                    for job in islice(todo, 1):
                        submit(job)
                    yield result
            finally:  # free the workers' CPUs now, for the next map's actors
                for a in actors:
                    ray.kill(a)

        yield ordered
