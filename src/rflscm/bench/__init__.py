"""Benchmarks behind ``rflscm bench NAME``: each returns a JSON-able dict and prints a table.

Speed and accuracy targets live here and in BENCHMARKS.md, never in timed unit tests.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any


@dataclass(frozen=True)
class BenchContext:
    """What every benchmark receives from the CLI."""

    size: str  # "quick" (2 CPU cores, minutes) or "full" (GPU)
    seeds: int
    out_dir: Path
    device: str
    scenario: str | None  # scenario directory; None = the shipped default
    config: str | None = None  # model preset or YAML for benchmarks that take one (b9: the new model's)
    baseline: str | None = None  # folder holding the baseline code's src, for benchmarks that compare with one (b9)
    sites: tuple[int, ...] = ()  # b10: network sizes (site counts); empty = the size's list
    minutes: float | None = None  # b10: also train RF-LSCM with this --minutes budget and evaluate it


BenchFn = Callable[[BenchContext], dict[str, Any]]
BENCHMARKS: dict[str, tuple[str, BenchFn]] = {}


def register_bench(name: str, summary: str) -> Callable[[BenchFn], BenchFn]:
    """Decorator adding a benchmark to :data:`BENCHMARKS`."""

    def wrap(fn: BenchFn) -> BenchFn:
        BENCHMARKS[name] = (summary, fn)
        return fn

    return wrap


def load_all() -> None:
    """Import the benchmark modules so that they register themselves."""
    from rflscm.bench import (  # noqa: F401
        b01_adjust,
        b02_convergence,
        b03_multifreq,
        b04_point_cloud,
        b05_alpha_p,
        b06_unseen,
        b07_optimize,
        b08_realism,
        b09_time_to_target,
        b10_scale,
        import_roundtrip,
        opt_speed,
        render_speed,
        sensing,
        wnomp_speed,
    )
