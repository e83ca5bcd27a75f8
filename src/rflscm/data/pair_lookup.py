"""Row of each (cell_id, grid_id) pair in a fixed table of pairs, by binary search on one int64 key per pair.

A model's answer looks its pairs up in several such tables (the posterior's pairs, the left-over pairs' WNOMP APS,
the renders the pass kept, the anchors, round 1's reported pairs).  ``pd.MultiIndex.from_arrays(...)`` and
``get_indexer`` cost ~0.5 ms a call even for a few hundred pairs (it factorises both levels each time); packing a
pair into one integer and ``np.searchsorted`` on the sorted keys costs ~0.02 ms (issue 29: RF-LSCM's answer at the
pairs it does not render; docs/DECISIONS.md, "Pair lookups by packed keys").
"""

from __future__ import annotations

import numpy as np
import pandas as pd

_LIMIT = 1 << 31
"""Ids in ``[0, 2³¹)`` pack into one int64 (cell in the high half, grid in the low); other ids fall back to pandas."""


def _ids(values: np.ndarray) -> np.ndarray:
    return np.asarray(values, dtype=np.int64).reshape(-1)


def _packable(cells: np.ndarray, grids: np.ndarray) -> bool:
    return not cells.size or bool(
        cells.min() >= 0 and cells.max() < _LIMIT and grids.min() >= 0 and grids.max() < _LIMIT
    )


class PairLookup:
    """The row of each asked (cell_id, grid_id) pair in the table ``(cell_ids [P], grid_ids [P])``, −1 where the table
    has none; the first row where a pair appears more than once."""

    def __init__(self, cell_ids: np.ndarray, grid_ids: np.ndarray) -> None:
        cells, grids = _ids(cell_ids), _ids(grid_ids)
        if cells.shape != grids.shape:
            raise ValueError(f"cell_ids and grid_ids differ in length ({cells.size} and {grids.size})")
        self.size = cells.size
        self._index: pd.MultiIndex | None = None
        if _packable(cells, grids):
            keys = (cells << 32) | grids
            self._order = np.argsort(keys, kind="stable")
            self._keys = keys[self._order]
        else:  # ids beyond 31 bits (an import's own numbering): pandas' hash index
            index = pd.MultiIndex.from_arrays([cells, grids])
            first = ~index.duplicated()
            self._index, self._rows = index[first], np.flatnonzero(first)

    @classmethod
    def of(cls, index: pd.MultiIndex) -> PairLookup:
        """The lookup of a two-level (cell_id, grid_id) index."""
        return cls(index.get_level_values(0).to_numpy(), index.get_level_values(1).to_numpy())

    @classmethod
    def kept_by(cls, holder: object, index: pd.MultiIndex) -> PairLookup:
        """The lookup of ``index``, built once and kept on ``holder`` while ``holder``'s table is that same index
        object (a table replaced by another gets a new lookup)."""
        kept = holder.__dict__.get("_pair_lookup")
        if kept is None or kept[0] is not index:
            kept = (index, cls.of(index))
            holder.__dict__["_pair_lookup"] = kept
        return kept[1]

    def rows(self, cell_ids: np.ndarray, grid_ids: np.ndarray) -> np.ndarray:
        """int64 ``[N]``: the table's row of each pair (``cell_ids``, ``grid_ids`` [N]), −1 where it has none."""
        cells, grids = _ids(cell_ids), _ids(grid_ids)
        out = np.full(cells.size, -1, dtype=np.int64)
        if not self.size or not cells.size:
            return out
        if self._index is not None:
            at = self._index.get_indexer(pd.MultiIndex.from_arrays([cells, grids]))
            found = at >= 0
            out[found] = self._rows[at[found]]
            return out
        ok = (cells >= 0) & (cells < _LIMIT) & (grids >= 0) & (grids < _LIMIT)
        keys = (cells[ok] << 32) | grids[ok]
        pos = np.minimum(np.searchsorted(self._keys, keys), self.size - 1)
        out[ok] = np.where(self._keys[pos] == keys, self._order[pos], -1)
        return out


__all__ = ["PairLookup"]
