"""Process-wide settings for CPU speed (the CLI applies them at start; nothing here knows about models).

**Freed memory stays in the process.**  glibc serves every allocation above its mmap threshold (128 KiB,
rising to at most 32 MiB as such blocks are freed) with a fresh ``mmap`` and returns it to the system on
``free``.  A render allocates tensors of tens of megabytes per chunk (``[decoder evaluations, 64]``
hidden activations, gathered rows), so each one is faulted in page by page again: gathering 200 k rows of
64 floats took 28 ms with a fresh allocation and 2.5 ms into an existing one (one thread).  Raising the
mmap and trim thresholds keeps freed blocks in the heap for the next chunk; the process does not hand
memory back between chunks, and its peak grows a little with fragmentation (`rflscm demo`: 1.6–1.7 GB
peak RSS before, 1.7–1.8 GB after; BENCHMARKS.md).  PyTorch's CPU tuning guide makes the
same point with jemalloc/tcmalloc; this uses glibc's own knobs, with no dependency.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
from collections.abc import Callable, Iterable, Iterator
from typing import Any

Mapper = Callable[[Callable[[Any], Any], Iterable[Any]], Iterator[Any]]
"""How a loop's jobs run: ``mapper(fn, jobs)`` → ``fn(job)`` for each job, in the jobs' order, like the built-in
``map`` (which is one; :func:`rflscm.parallel.work.mapper` gives one over Ray workers).  ``fn`` must pickle."""

MMAP_THRESHOLD = 1 << 30
"""Allocations up to 1 GiB come from the heap (glibc's default: 128 KiB, adapting up to 32 MiB)."""
TRIM_THRESHOLD = (1 << 31) - 1
"""Free memory at the heap's top is kept up to 2 GiB (glibc's default: 128 KiB, adapting)."""
MALLOC_ENV = {"MALLOC_MMAP_THRESHOLD_": str(MMAP_THRESHOLD), "MALLOC_TRIM_THRESHOLD_": str(TRIM_THRESHOLD)}
"""The same settings for a child process (glibc reads them at start): benchmarks give them to every worker."""
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # mallopt parameters (malloc.h)


def keep_freed_memory() -> bool:
    """Raise glibc's mmap and trim thresholds for this process; True when applied, False where the C library
    is not glibc (macOS, musl, Windows) or the environment already sets them (the user's choice wins)."""
    if any(key in os.environ for key in MALLOC_ENV):
        return False
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name) if name else None
        mallopt = getattr(libc, "mallopt", None)
        gnu = getattr(libc, "gnu_get_libc_version", None)
    except OSError:
        return False
    if mallopt is None or gnu is None:  # mallopt's parameter numbers are glibc's
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
