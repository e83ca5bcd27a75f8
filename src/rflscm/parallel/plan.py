"""Chunk planning without ray: which ``aps`` calls the serial path makes, and how they split over workers.

Bit-identical results need the workers to make *the same* calls as the serial path (a batch of another size
may round differently in the last bit), so the plan replays the serial path instead of cutting pairs anew:
:func:`predict_blocks` is :func:`rflscm.models.source.predict_rsrp`'s split (cell by cell, in blocks of
``chunk`` pairs) and :func:`cache_misses` is :class:`rflscm.eval.cache.APSCache`'s (a block asks its source
only for the pairs not answered before, each once).  :func:`split_even` then groups whole calls into
contiguous chunks of similar size; concatenating the chunks' answers gives back the calls' order.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

PREDICT_CHUNK = 4096  # rflscm.models.source.predict_rsrp's default block


@dataclass(frozen=True)
class Call:
    """One ``source.aps(cell_ids, grid_ids)`` call of the serial path (pairs in its order)."""

    cell_ids: np.ndarray
    grid_ids: np.ndarray

    def __len__(self) -> int:
        return len(self.cell_ids)


def predict_blocks(cell_ids: np.ndarray, chunk: int = PREDICT_CHUNK) -> list[np.ndarray]:
    """Row indices of the blocks ``predict_rsrp`` asks its source for: cell by cell (sorted ids), rows in
    their order, at most ``chunk`` per block."""
    cell_ids = np.asarray(cell_ids).reshape(-1)
    blocks: list[np.ndarray] = []
    for cell in np.unique(cell_ids):
        rows = np.flatnonzero(cell_ids == cell)
        blocks.extend(rows[start : start + chunk] for start in range(0, len(rows), chunk))
    return blocks


def cache_misses(
    requests: Iterable[tuple[np.ndarray, np.ndarray]], known: set[tuple[int, int]] | None = None
) -> list[Call]:
    """The calls an APS cache makes on its source for ``requests`` (``(cell_ids, grid_ids)`` asked of the cache,
    in order): per request, the pairs not answered before (``known``, updated), each at its first position."""
    known = set() if known is None else known
    calls = []
    for cells, grids in requests:
        cells, grids = np.asarray(cells).reshape(-1), np.asarray(grids).reshape(-1)
        keys = list(zip(cells.tolist(), grids.tolist(), strict=True))
        todo, seen = [], set()
        for i, key in enumerate(keys):
            if key not in known and key not in seen:
                todo.append(i)
            seen.add(key)
        if todo:
            calls.append(Call(cells[todo], grids[todo]))
            known.update(keys[i] for i in todo)
    return calls


def split_even(sizes: list[int], num_chunks: int) -> list[range]:
    """Contiguous ranges of item indices, ``num_chunks`` at most, each close to ``sum(sizes) / num_chunks``.

    Items are never cut, never reordered and every one lands in exactly one range; empty ranges are dropped.
    """
    if num_chunks < 1:
        raise ValueError(f"num_chunks must be at least 1 (got {num_chunks})")
    total = sum(sizes)
    if not sizes:
        return []
    bounds, start, done = [], 0, 0
    for k in range(1, num_chunks):
        target = total * k / num_chunks
        end = start
        while end < len(sizes) and (end == start or done + sizes[end] <= target):
            done += sizes[end]
            end += 1
        if end > start:
            bounds.append(range(start, end))
            start = end
    bounds.append(range(start, len(sizes)))
    return [b for b in bounds if len(b)]
