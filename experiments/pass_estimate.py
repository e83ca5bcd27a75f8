"""A checkpoint's measured pass estimate against what the pass takes, without a clock and within an ample budget
(issue 28: what a budget keeps for the pass after training).

Usage (from the repository root, which puts ``pass_model.py`` on the path):

    PYTHONPATH=src python experiments/pass_estimate.py CHECKPOINT SCENARIO [THREADS]

Prints ``EST`` (``finish_seconds`` on the final weights, twice: the first pays the renderer's first use), then
``PASS`` for the pass without a clock and within a budget too long to bind (as ``rflscm demo`` runs it, the pairs
it leaves rendered by the pass), each with its wall time and the seconds spent in its steps (renders, chunk
preparation, the first pairs, λ's and the dB mix's choices, WNOMP's solves, the left-over choice).
"""

from __future__ import annotations

import functools
import sys
import time

import torch
from pass_model import model_before_its_pass

import rflscm.models.rflscm.corrections as C
from rflscm.data import load_scenario

SPENT: dict[str, float] = {}


def timed(owner: object, name: str) -> None:
    """Wrap ``owner.name`` so that its seconds add up in ``SPENT`` (a generator's between its yields)."""
    inner = getattr(owner, name)

    if name == "chunks":

        def generator(*args, **kwargs):
            it = inner(*args, **kwargs)
            while True:
                t = time.perf_counter()
                try:
                    value = next(it)
                except StopIteration:
                    SPENT[name] = SPENT.get(name, 0.0) + time.perf_counter() - t
                    return
                SPENT[name] = SPENT.get(name, 0.0) + time.perf_counter() - t
                yield value

        setattr(owner, name, generator)
        return

    @functools.wraps(inner)
    def wrapper(*args, **kwargs):
        t = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            SPENT[name] = SPENT.get(name, 0.0) + time.perf_counter() - t

    setattr(owner, name, wrapper)


def main(checkpoint: str, scenario: str, threads: int = 1) -> None:
    torch.set_num_threads(threads)
    sc = load_scenario(scenario)
    model = model_before_its_pass(sc, checkpoint)
    for i in range(2):
        t0 = time.perf_counter()
        cost = model.finish_seconds()
        print(f"EST {i} total_s {cost.total_s:.2f} least_s {cost.least_s:.2f} ({time.perf_counter() - t0:.2f} s)")
    for name in ("_first_pairs", "_choose", "_mix_plan", "_left_over"):
        timed(C, name)
    for name in ("render_pairs", "chunks", "fallback", "render_only"):
        timed(C._Fit, name)
    for mode in ("no clock", "ample budget"):
        SPENT.clear()
        model = model_before_its_pass(sc, checkpoint)
        t0 = time.perf_counter()
        end = t0 + 1e6
        budget = {} if mode == "no clock" else {"time_left": lambda: end - time.perf_counter(), "render_rest": True}
        model.finish_training(progress=False, **budget)
        spent = {k: round(v, 2) for k, v in SPENT.items()}
        print(f"PASS {mode}: {time.perf_counter() - t0:.2f} s", spent, model.run_info.get("corrections"), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else 1)
