"""A source's APS computed by Ray workers in chunks, filled into the APS cache the serial code reads.

The serial code (``rflscm predict``, :func:`rflscm.eval.run_evaluation`) asks an
:class:`~rflscm.eval.cache.APSCache` for its pairs' APS.  Here the same calls it would make on the model are
planned (:mod:`rflscm.parallel.plan`), answered by workers that each load the checkpoint once, and stored in
the cache before the serial code runs; the serial code then finds every pair answered and does the cheap rest
(sensing matrices, dB, tables) in its own order.  A call a worker cannot answer (:class:`UnsupportedError`)
stays unanswered, so the serial code meets the same refusal it would have met alone.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
import torch
from tqdm.auto import tqdm

from rflscm.data import BEAM_TYPES
from rflscm.data.measurements import reported_pairs
from rflscm.errors import ConfigError, RflscmError, UnsupportedError
from rflscm.eval.cache import APSCache, render_rows
from rflscm.parallel.engine import Engine, ray_session
from rflscm.parallel.plan import Call, cache_misses, predict_blocks, split_even

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.eval.protocols import Protocol
    from rflscm.models.source import APSSource

CHUNKS_PER_WORKER = 4  # more chunks than workers, so that a slow chunk does not hold the others up

SparseRows = list[tuple[np.ndarray, np.ndarray]]  # per pair: (nonzero bins, their values), as APSCache keeps them
Answer = SparseRows | None  # None: the source refused the call (UnsupportedError)
Task = tuple[np.ndarray, np.ndarray, np.ndarray | None]  # (cell_ids, grid_ids, grid_xyz) of one call


class FilledAPSCache(APSCache):
    """An :class:`APSCache` that also takes rows computed elsewhere (by workers, from the same source)."""

    def fill(self, call: Call, rows: SparseRows) -> None:
        """Store ``rows`` (one per pair of ``call``, in order) as the cache's answer for ``call``'s pairs."""
        if len(rows) != len(call):
            raise RflscmError(f"a worker answered {len(rows)} APS rows for a call of {len(call)} pairs")
        # concatenated into the store's own tensors: Ray hands out read-only views of its object store (torch warns
        # on those), and the cache outlives the worker's answer
        self._rows.add_sparse(list(zip(call.cell_ids.tolist(), call.grid_ids.tolist(), strict=True)), rows)

    filled: int = 0  # pairs filled from elsewhere

    def known(self) -> set[tuple[int, int]]:
        """The pairs answered so far."""
        return self._rows.keys()


def sparse_rows(x: torch.Tensor) -> SparseRows:
    """Rows of an APS ``[num_pairs, num_bins]`` as APSCache keeps them: (nonzero bins, values) per pair."""
    x = x.detach().cpu()
    if not x.shape[0]:
        return []
    at, bins = torch.nonzero(x, as_tuple=True)
    values = x[at, bins].numpy()
    cut = np.cumsum(torch.bincount(at, minlength=x.shape[0]).numpy())[:-1]
    return list(zip(np.split(bins.numpy(), cut), np.split(values, cut), strict=True))


def answer(source: APSSource, tasks: Sequence[Task]) -> list[Answer]:
    """``source.aps`` of each task, sparse, in order; None where the source refuses (UnsupportedError)."""
    out: list[Answer] = []
    for cells, grids, xyz in tasks:
        try:
            with torch.no_grad():
                out.append(sparse_rows(source.aps(cells, grids, xyz)))
        except UnsupportedError:
            out.append(None)
    return out


def scatter(tasks: Sequence[Task], num_chunks: int) -> list[list[Task]]:
    """Contiguous chunks of whole tasks of similar pair counts, in order."""
    return [[tasks[i] for i in r] for r in split_even([len(t[0]) for t in tasks], num_chunks)]


def gather(chunks: Sequence[Sequence[Task]], answers: Sequence[Sequence[Answer]]) -> list[Answer]:
    """The chunks' answers concatenated in the chunks' order, refusing a chunk answered with the wrong shape."""
    if len(answers) != len(chunks):
        raise RflscmError(f"{len(answers)} answers came back for {len(chunks)} chunks")
    out: list[Answer] = []
    for k, (chunk, got) in enumerate(zip(chunks, answers, strict=True)):
        if len(got) != len(chunk):
            raise RflscmError(f"chunk {k}: a worker answered {len(got)} of its {len(chunk)} calls")
        for (cells, _, _), rows in zip(chunk, got, strict=True):
            if rows is not None and len(rows) != len(cells):
                raise RflscmError(f"chunk {k}: a worker answered {len(rows)} APS rows for a call of {len(cells)} pairs")
        out.extend(got)
    return out


class _Worker:
    """A Ray actor: loads its source once (``load()``), then answers chunks of calls."""

    def __init__(self, load: Callable[[], APSSource], threads: int) -> None:
        torch.set_num_threads(threads)  # the driver's --threads: one thread per worker gives bit-identical results
        self.source = load()

    def answer(self, tasks: list[Task]) -> list[Answer]:
        return answer(self.source, tasks)


def load_checkpoint(checkpoint: str, scenario: str, device: str) -> APSSource:
    """The fitted model of ``checkpoint`` on the scenario folder ``scenario`` (what a worker loads once)."""
    from rflscm.data import load_scenario
    from rflscm.models import load_model

    return load_model(checkpoint, load_scenario(scenario), device=device)


def checkpoint_loader(
    checkpoint: str | object, scenario: str | object, device: torch.device | str
) -> Callable[[], APSSource]:
    """A picklable ``load()`` of a checkpoint on a scenario folder, for the workers (paths must be readable there)."""
    from pathlib import Path

    return partial(
        load_checkpoint, str(Path(str(checkpoint)).resolve()), str(Path(str(scenario)).resolve()), str(device)
    )


def run_ray(engine: Engine, load: Callable[[], APSSource], chunks: list[list[Task]]) -> list[list[Answer]]:
    """Each chunk answered by one of ``engine.workers`` Ray actors; answers in the chunks' order."""
    with ray_session(engine) as ray:
        from ray.util import ActorPool

        worker = ray.remote(num_cpus=1)(_Worker)
        threads = torch.get_num_threads()
        actors = [worker.remote(load, threads) for _ in range(max(1, min(engine.workers, len(chunks))))]
        try:
            answers = ActorPool(actors).map(lambda actor, chunk: actor.answer.remote(chunk), chunks)
            desc = f"rendering APS on {len(actors)} Ray workers"
            return list(tqdm(answers, total=len(chunks), desc=desc, unit="chunk", leave=False, disable=None))
        except ray.exceptions.RayError as exc:
            cause = getattr(exc, "cause", None)
            if isinstance(cause, RflscmError):
                raise cause from None
            raise RflscmError(f"a Ray worker failed: {str(exc).strip().splitlines()[-1]}") from None


Runner = Callable[[list[list[Task]]], list[list[Answer]]]


def fill_cache(
    cache: FilledAPSCache,
    scenario: Scenario,
    requests: Sequence[tuple[np.ndarray, np.ndarray]],
    num_chunks: int,
    run: Runner,
) -> int:
    """Answer, through ``run``, the calls ``requests`` would make on ``cache``'s source, and store them in
    ``cache``.  Returns the number of pairs filled."""
    calls = cache_misses(requests, cache.known())
    if not calls:
        return 0
    xyz = scenario.grids.set_index("grid_id")[["x", "y", "z"]]
    tasks: list[Task] = [(c.cell_ids, c.grid_ids, xyz.loc[c.grid_ids].to_numpy()) for c in calls]
    chunks = scatter(tasks, num_chunks)
    filled = 0
    for call, rows in zip(calls, gather(chunks, run(chunks)), strict=True):
        if rows is not None:
            cache.fill(call, rows)
            filled += len(rows)
    cache.filled += filled
    return filled


def filled_cache(
    model: APSSource,
    scenario: Scenario,
    requests: Sequence[tuple[np.ndarray, np.ndarray]],
    engine: Engine,
    load: Callable[[], APSSource],
) -> FilledAPSCache:
    """An APS cache of ``model`` holding, when ``engine`` is parallel, the answers to ``requests`` computed by
    Ray workers (each ``load()``-ing its own copy of the model); with one in-process worker, an empty one."""
    cache = FilledAPSCache(model)
    if engine.parallel and model.device.type != "cpu":
        raise ConfigError(f"--workers > 1 and --ray-address run on CPU workers; add --device cpu (got {model.device}).")
    if engine.parallel:
        fill_cache(cache, scenario, requests, engine.workers * CHUNKS_PER_WORKER, partial(run_ray, engine, load))
    return cache


def prediction_requests(pairs: pd.DataFrame) -> list[tuple[np.ndarray, np.ndarray]]:
    """What ``predict_rsrp(cache, …, pairs)`` asks its cache for (the second beam type asks nothing new)."""
    cells, grids = pairs["cell_id"].to_numpy(), pairs["grid_id"].to_numpy()
    return [(cells[b], grids[b]) for b in predict_blocks(cells)]


def prediction_cache(
    model: APSSource, scenario: Scenario, pairs: pd.DataFrame, engine: Engine, load: Callable[[], APSSource]
) -> FilledAPSCache:
    """The APS cache ``rflscm predict`` reads for ``pairs``, filled in parallel when ``engine`` is."""
    return filled_cache(model, scenario, prediction_requests(pairs), engine, load)


def evaluation_requests(
    model: APSSource, scenario: Scenario, protocol: Protocol
) -> list[tuple[np.ndarray, np.ndarray]]:
    """What :func:`rflscm.eval.run_evaluation` asks its model for under ``protocol``: per beam type, the test
    pairs it scores (all, or only the trained ones for a model without unseen grids), cell by cell in blocks."""
    train = protocol.training_scenario(scenario)
    seen_index = pd.MultiIndex.from_frame(reported_pairs(train.measurements))
    test = protocol.test_set(scenario)
    requests = []
    for beam_type in BEAM_TYPES:
        pairs, _ = test.tables[beam_type]
        if not len(pairs):
            continue
        if not model.supports_unseen_grids:
            pairs = pairs[np.asarray(pd.MultiIndex.from_frame(pairs[["cell_id", "grid_id"]]).isin(seen_index))]
        requests.extend(prediction_requests(pairs))
    return requests


def evaluation_cache(
    model: APSSource, scenario: Scenario, protocol: Protocol, engine: Engine, load: Callable[[], APSSource]
) -> FilledAPSCache:
    """The model as :func:`rflscm.eval.run_evaluation` should get it: its APS of the test pairs computed in
    parallel when ``engine`` is (the evaluation then only reads them)."""
    requests = evaluation_requests(model, scenario, protocol) if engine.parallel else []
    return filled_cache(model, scenario, requests, engine, load)


def render_requests(
    model: APSSource,
    scenario: Scenario,
    chunk: int = 1024,
    free_cells: np.ndarray | None = None,
    measured: bool = False,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """What :meth:`rflscm.eval.cache.ScenarioAPS.render` (the optimiser's APS) asks its source for: cell by
    cell, the grids in reach (:func:`rflscm.eval.cache.render_rows`), in blocks of ``chunk``."""
    grid_ids = scenario.grid_ids()
    requests = []
    for cell, rows in zip(scenario.cell_ids(), render_rows(model, scenario, free_cells, measured), strict=True):
        for start in range(0, len(rows), chunk):
            sel = rows[start : start + chunk]
            requests.append((np.full(len(sel), cell), grid_ids[sel]))
    return requests


def render_cache(
    model: APSSource,
    scenario: Scenario,
    engine: Engine,
    load: Callable[[], APSSource],
    free_cells: np.ndarray | None = None,
    measured: bool = False,
) -> FilledAPSCache:
    """The model as ``ScenarioAPS.render`` / ``load_or_render`` (``rflscm optimize``) should get it: every APS
    it renders computed by Ray workers first when ``engine`` is parallel (the render then only reads them)."""
    requests = render_requests(model, scenario, free_cells=free_cells, measured=measured) if engine.parallel else []
    return filled_cache(model, scenario, requests, engine, load)
