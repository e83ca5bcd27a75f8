"""Small timing helpers for benchmarks."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch


def time_call(fn: Callable[[], object], repeats: int = 20, warmup: int = 3, device: str = "cpu") -> dict[str, float]:
    """Wall time of ``fn()`` over ``repeats`` runs after ``warmup`` runs: min / median / max [ms]."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        times.append((time.perf_counter() - t0) * 1e3)
    arr = np.asarray(times)
    return {
        "min_ms": float(arr.min()),
        "median_ms": float(np.median(arr)),
        "max_ms": float(arr.max()),
        "repeats": repeats,
    }
