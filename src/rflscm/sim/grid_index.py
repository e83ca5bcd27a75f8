"""A uniform 2-D grid over x/y that finds which rectangles or points a segment, a wedge or a box may meet.

The procedural tracer (:mod:`rflscm.sim.procedural`) tests segments against building boxes and reflection
images against receivers.  Against every box and every receiver its cost per receiver grew with the whole
city (issue 29: ~buildings^1.4).  :class:`CellGrid` bins items (axis-aligned x/y rectangles, points as
zero-size ones) into square cells; a query lists the (query, item) pairs whose cells the query's region
touches.  Queries are conservative: every item whose closed rectangle meets the query's closed region is
listed (items are binned with a margin far above rounding), and some that do not; the caller runs its exact
test on the listed pairs only, so its results are those of the test against all items.
"""

from __future__ import annotations

import numpy as np

BIN_MARGIN_M = 1e-3
"""Items are binned as if this much larger on every side [m], far above the rounding of the queries."""


def _expand(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(owner, rank)`` for ``counts[i]`` rows per owner i: owner ids and 0…counts[i]−1 within each."""
    counts = np.asarray(counts, dtype=np.int64)
    owner = np.repeat(np.arange(len(counts)), counts)
    starts = np.cumsum(counts) - counts
    rank = np.arange(len(owner)) - starts[owner]
    return owner, rank


class CellGrid:
    """Rectangles ``lo [n, 2]`` … ``hi [n, 2]`` [m] binned into square cells of side ``cell_m`` [m].

    Cells are numbered ``ix · ny + iy``; the grid covers the items' extent (plus the margin).  Each cell lists
    its items in item order.
    """

    def __init__(self, lo: np.ndarray, hi: np.ndarray, cell_m: float) -> None:
        lo = np.asarray(lo, dtype=np.float64).reshape(-1, 2) - BIN_MARGIN_M
        hi = np.asarray(hi, dtype=np.float64).reshape(-1, 2) + BIN_MARGIN_M
        if not cell_m > 0:
            raise ValueError(f"cell_m must be > 0 (got {cell_m})")
        self.cell_m = float(cell_m)
        self.num_items = len(lo)
        self.origin = lo.min(axis=0) if len(lo) else np.zeros(2)
        top = hi.max(axis=0) if len(hi) else np.zeros(2)
        self.shape = np.maximum(np.floor((top - self.origin) / self.cell_m).astype(np.int64) + 1, 1)
        c0 = self._clip(np.floor((lo - self.origin) / self.cell_m), self.shape)
        c1 = self._clip(np.floor((hi - self.origin) / self.cell_m), self.shape)
        span = c1 - c0 + 1
        item, rank = _expand(span[:, 0] * span[:, 1])
        ix = c0[item, 0] + rank // span[item, 1]
        iy = c0[item, 1] + rank % span[item, 1]
        cell = ix * self.shape[1] + iy
        order = np.argsort(cell, kind="stable")  # within a cell, items stay in item order
        self.items = item[order]
        self.start = np.searchsorted(cell[order], np.arange(self.num_cells + 1))

    @property
    def num_cells(self) -> int:
        return int(self.shape[0] * self.shape[1])

    def _clip(self, index: np.ndarray, size: np.ndarray | int) -> np.ndarray:
        """Cell indices clipped to ``0 … size − 1``."""
        return np.clip(index, 0, np.asarray(size) - 1).astype(np.int64)

    def _grid(self, xy: np.ndarray) -> np.ndarray:
        return (np.asarray(xy, dtype=np.float64) - self.origin) / self.cell_m

    # ---- from cells to items --------------------------------------------------------------------------
    def items_of(self, owner: np.ndarray, cell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(owner, item)`` pairs: every item of every (owner, cell) pair (duplicates where an item spans cells)."""
        count = self.start[cell + 1] - self.start[cell]
        row, rank = _expand(count)
        return owner[row], self.items[self.start[cell[row]] + rank]

    def unique_items(self, owner: np.ndarray, cell: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`items_of` without duplicates, sorted by owner then item."""
        own, item = self.items_of(owner, cell)
        n = max(self.num_items, 1)
        key = np.unique(own * n + item)
        return key // n, key % n

    # ---- queries: (query, cell) pairs -------------------------------------------------------------------
    def point_cells(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(point, cell)``: the cell of each point ``xy [m, 2]`` that lies on the grid."""
        g = np.floor(self._grid(xy).reshape(-1, 2))
        on = np.all((g >= 0) & (g < self.shape), axis=1)
        idx = np.flatnonzero(on)
        return idx, g[idx, 0].astype(np.int64) * self.shape[1] + g[idx, 1].astype(np.int64)

    def rect_cells(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(rect, cell)``: the cells that closed rectangles ``lo [m, 2]`` … ``hi [m, 2]`` touch."""
        g0, g1 = self._grid(lo).reshape(-1, 2), self._grid(hi).reshape(-1, 2)
        on = np.all((g1 >= 0) & (g0 < self.shape), axis=1)
        c0, c1 = self._clip(np.floor(g0), self.shape), self._clip(np.floor(g1), self.shape)
        span = np.where(on[:, None], c1 - c0 + 1, 0)
        rect, rank = _expand(span[:, 0] * span[:, 1])
        ix = c0[rect, 0] + rank // np.maximum(span[rect, 1], 1)
        iy = c0[rect, 1] + rank % np.maximum(span[rect, 1], 1)
        return rect, ix * self.shape[1] + iy

    def segment_cells(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(segment, cell)``: the cells that the x/y projections of segments ``a → b [m, ≥2]`` run through.

        Column by column of cells along x, the rows between the segment's y where it enters and leaves the
        column (its whole y extent where it runs along y).
        """
        g0, g1 = self._grid(np.asarray(a)[:, :2]), self._grid(np.asarray(b)[:, :2])
        lo, hi = np.minimum(g0, g1), np.maximum(g0, g1)
        on = np.all((hi >= 0) & (lo < self.shape), axis=1)
        c0, c1 = self._clip(np.floor(lo[:, 0]), self.shape[0]), self._clip(np.floor(hi[:, 0]), self.shape[0])
        seg, rank = _expand(np.where(on, c1 - c0 + 1, 0))
        col = c0[seg] + rank
        x0, x1 = np.maximum(col, lo[seg, 0]), np.minimum(col + 1.0, hi[seg, 0])
        dx = g1[seg, 0] - g0[seg, 0]
        steep = np.abs(dx) < 1e-3  # within a thousandth of a cell of vertical: its whole y extent
        slope = np.where(steep, 0.0, (g1[seg, 1] - g0[seg, 1]) / np.where(steep, 1.0, dx))
        y0 = g0[seg, 1] + (x0 - g0[seg, 0]) * slope
        y1 = g0[seg, 1] + (x1 - g0[seg, 0]) * slope
        tol = 1e-12 * np.abs(slope) * (1.0 + np.abs(g0[seg, 0]) + np.abs(x1))  # rounding of x0, x1 times slope
        y_lo = np.where(steep, lo[seg, 1], np.maximum(np.minimum(y0, y1) - tol, lo[seg, 1]))
        y_hi = np.where(steep, hi[seg, 1], np.minimum(np.maximum(y0, y1) + tol, hi[seg, 1]))
        return self._column_runs(seg, col, y_lo, y_hi, axis=0)

    def wedge_cells(
        self,
        image: np.ndarray,
        axis: np.ndarray,
        coord: np.ndarray,
        sign: np.ndarray,
        u_lo: np.ndarray,
        u_hi: np.ndarray,
        margin_m: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(wedge, cell)``: the cells of the points P in front of a wall whose line from a point behind it
        crosses the wall.

        Wedge k: the wall is the plane ``x[axis[k]] = coord[k]`` facing ``sign[k]``, spanning
        ``u_lo[k] … u_hi[k]`` (grown by ``margin_m``) along the other horizontal axis; ``image [k, ≥2]`` lies
        behind it.  Lists the cells of the points P on the front side (``sign · (P − coord) ≥ 0``) for which
        the line image → P crosses the wall plane within that span; none for an image not strictly behind.
        """
        image = np.asarray(image, dtype=np.float64)[:, :2]
        axis = np.asarray(axis, dtype=np.int64)
        rows = np.arange(len(axis))
        g_img = self._grid(image)
        img_a, img_u = g_img[rows, axis], g_img[rows, 1 - axis]
        origin_a, origin_u = self.origin[axis], self.origin[1 - axis]
        wall = (coord - origin_a) / self.cell_m
        e_lo = (u_lo - margin_m - origin_u) / self.cell_m
        e_hi = (u_hi + margin_m - origin_u) / self.cell_m
        depth = sign * (wall - img_a)  # image behind the wall by this much [cells]
        n_a = self.shape[axis]
        first = np.clip(np.floor(wall), -1, n_a).astype(np.int64)
        layers = np.where(sign > 0, n_a - np.maximum(first, 0), np.minimum(first, n_a - 1) + 1)
        layers = np.where(depth > 0, np.maximum(layers, 0), 0)
        k, rank = _expand(layers)
        layer = np.where(sign[k] > 0, np.maximum(first[k], 0) + rank, np.minimum(first[k], n_a[k] - 1) - rank)
        s = sign[k, None] * (np.stack([layer, layer + 1.0], axis=1) - wall[k, None])  # [rows, 2] depth in front
        s = np.maximum(s, 0.0)
        with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
            scale = (depth[k, None] + s) / depth[k, None]
            ends = [img_u[k, None] + (e[k, None] - img_u[k, None]) * scale for e in (e_lo, e_hi)]
        both = np.concatenate(ends, axis=1)
        finite = np.isfinite(both).all(axis=1)
        v_lo = np.where(finite, both.min(axis=1), 0.0)  # a wedge too wide to compute: the whole range
        v_hi = np.where(finite, both.max(axis=1), self.shape[1 - axis[k]].astype(np.float64))
        return self._column_runs(k, layer, v_lo, v_hi, axis=axis[k])

    def _column_runs(
        self, owner: np.ndarray, col: np.ndarray, v_lo: np.ndarray, v_hi: np.ndarray, axis: np.ndarray | int
    ) -> tuple[np.ndarray, np.ndarray]:
        """Expand (owner, index ``col`` along ``axis``, range ``v_lo … v_hi`` [cells] along the other axis) to
        ``(owner, cell)`` pairs (ranges grown by a hair, clipped to the grid)."""
        axis = np.broadcast_to(np.asarray(axis, dtype=np.int64), col.shape)
        n_v = np.where(axis == 0, self.shape[1], self.shape[0])
        v_lo, v_hi = v_lo - 1e-9, v_hi + 1e-9
        on = (v_hi >= 0) & (v_lo < n_v)
        r0 = np.clip(np.floor(v_lo), 0, n_v - 1).astype(np.int64)
        r1 = np.clip(np.floor(v_hi), 0, n_v - 1).astype(np.int64)
        row, rank = _expand(np.where(on, r1 - r0 + 1, 0))
        v = r0[row] + rank
        ix = np.where(axis[row] == 0, col[row], v)
        iy = np.where(axis[row] == 0, v, col[row])
        return owner[row], ix * self.shape[1] + iy
