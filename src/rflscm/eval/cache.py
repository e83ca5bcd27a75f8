"""The APS cache of evaluation, prediction and optimisation: a source's APS computed once, kept safely.

Two views of one thing, in one module, with one key:

* :class:`APSCache` remembers, in memory, the APS of each (cell, grid) pair a source was asked for.  Evaluation
  asks for a pair once per beam type (through ``predict_rsrp``) and again for the APS metrics, the benchmarks
  again, ``rflscm predict`` once per beam type; a field model would render each time.  Rows are stored sparse
  (the nonzero bins), so a cache of every test pair fits in memory even at full size.
* :class:`ScenarioAPS` is the APS of every (cell, grid) pair of a scenario within reach (:func:`render_rows`),
  per cell on the bins any of its grids uses: what the optimiser searches on (``rflscm optimize --aps-cache``),
  and the one cache written to disk.

A cache file holds tensors, numbers and text only, read with ``torch.load(weights_only=True)`` (nothing is ever
unpickled), with a SHA-256 over its content and the key of its source (:func:`~rflscm.models.source.
source_sha256`: for a model, the content hash of its checkpointed state).  :func:`ScenarioAPS.load` refuses, in
one line, a file that is not a cache, a damaged one, one written for another checkpoint, grid or scenario, and
one whose APS are not finite and ≥ 0.
"""

from __future__ import annotations

import os
import pickle
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from rflscm.data.safe_io import is_zip_archive
from rflscm.errors import RflscmError
from rflscm.geometry import AngleGrid
from rflscm.models.base import content_hash
from rflscm.models.source import APSSource, Predicts, RsrpMix, checked_aps, rsrp_mix_of, source_sha256

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario

CACHE_FORMAT = "rflscm-aps-cache/2"
"""/2: each cell's APS holds the rows of its grids within reach only (``known``); /1 held every grid's row."""

REACH_MARGIN = 1.25
"""A field model's APS is rendered at the grids within this × the network's hearing range of a cell
(:func:`render_rows`): a quarter beyond the farthest round-1 report, where a changed tilt or azimuth may still
push a cell's signal."""


class APSCacheError(RflscmError):
    """An APS cache file cannot be used: not a cache, damaged, of another source or scenario, or non-finite."""


class SparseRowStore:
    """APS rows by ``(cell_id, grid_id)``, kept sparse in blocks (each as it was added: row offsets, nonzero bins,
    values), so that a cache of hundreds of thousands of pairs costs its nonzeros and not a tensor object per pair,
    and is stored and read back with a few vectorised operations per block."""

    def __init__(self, num_bins: int, device: torch.device | str) -> None:
        self.num_bins, self.device = num_bins, torch.device(device)
        self._where: dict[tuple[int, int], tuple[int, int]] = {}  # key → (block, row)
        self._blocks: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []  # (offsets [n+1], bins, values)

    def __len__(self) -> int:
        return len(self._where)

    def __contains__(self, key: object) -> bool:
        return key in self._where

    def keys(self) -> set[tuple[int, int]]:
        return set(self._where)

    def add(self, keys: list[tuple[int, int]], rows: torch.Tensor) -> None:
        """Keep the dense ``rows [len(keys), num_bins]`` as each key's row (a later add of a key replaces it)."""
        rows = rows.detach()
        at, bins = torch.nonzero(rows, as_tuple=True)
        counts = torch.bincount(at, minlength=len(keys))
        self._add_block(keys, counts, bins, rows[at, bins])

    def add_sparse(self, keys: list[tuple[int, int]], rows: list[tuple[np.ndarray, np.ndarray]]) -> None:
        """Keep ``rows`` (per key: its nonzero bins and their values, as workers answer them)."""
        counts = torch.as_tensor([len(b) for b, _ in rows], dtype=torch.long)
        bins = torch.as_tensor(np.concatenate([b for b, _ in rows]) if rows else np.zeros(0), dtype=torch.long)
        values = torch.as_tensor(np.concatenate([v for _, v in rows]) if rows else np.zeros(0), dtype=torch.float32)
        self._add_block(keys, counts, bins, values)

    def _add_block(
        self, keys: list[tuple[int, int]], counts: torch.Tensor, bins: torch.Tensor, values: torch.Tensor
    ) -> None:
        offsets = torch.zeros(len(keys) + 1, dtype=torch.long)
        offsets[1:] = torch.cumsum(counts.cpu(), 0)
        block = len(self._blocks)
        small = torch.int16 if self.num_bins < 2**15 else torch.int32
        self._blocks.append((offsets, bins.to(small).cpu(), values.float().cpu()))
        for row, key in enumerate(keys):
            self._where[key] = (block, row)

    def dense(self, keys: list[tuple[int, int]]) -> torch.Tensor:
        """``[len(keys), num_bins]`` the kept rows of ``keys`` (each must be kept)."""
        out = torch.zeros(len(keys), self.num_bins)
        if keys:
            where = np.array([self._where[k] for k in keys], dtype=np.int64).reshape(-1, 2)
            for block in np.unique(where[:, 0]):
                mine = np.flatnonzero(where[:, 0] == block)
                offsets, bins, values = self._blocks[int(block)]
                rows = torch.as_tensor(where[mine, 1])
                start, count = offsets[rows], offsets[rows + 1] - offsets[rows]
                first = torch.cumsum(count, 0) - count  # each row's first place among the gathered nonzeros
                flat = torch.arange(int(count.sum())) - torch.repeat_interleave(first - start, count)
                dst = torch.repeat_interleave(torch.as_tensor(mine), count)
                out[dst, bins[flat].long()] = values[flat]
        return out.to(self.device)


class APSCache(Predicts):
    """A view of the fitted source ``inner`` that remembers its APS per ``(cell_id, grid_id)``.

    Everything but :meth:`aps` is the wrapped source's (name, fingerprint, run information).  Only use it while
    ``inner``'s weights do not change.
    """

    def __init__(self, inner: APSSource) -> None:
        self.inner = inner
        self._rows = SparseRowStore(inner.angle_grid.num_bins, inner.device)
        self._sha256: str | None = None

    @staticmethod
    def of(source: APSSource) -> APSCache:
        """``source`` itself when it is a cache already, else a fresh cache of it."""
        return source if isinstance(source, APSCache) else APSCache(source)

    # the wrapped source's facts
    @property
    def name(self) -> str:
        return self.inner.name

    @property
    def angle_grid(self) -> AngleGrid:
        return self.inner.angle_grid

    @property
    def device(self) -> torch.device:
        return self.inner.device

    @property
    def supports_unseen_grids(self) -> bool:
        return self.inner.supports_unseen_grids

    @property
    def fingerprint(self) -> str | None:
        return self.inner.fingerprint

    @property
    def run_info(self) -> dict[str, Any]:
        return self.inner.run_info

    def content_sha256(self) -> str:
        """The wrapped source's key (:func:`~rflscm.models.source.source_sha256`)."""
        if self._sha256 is None:
            self._sha256 = source_sha256(self.inner)
        return self._sha256

    def __len__(self) -> int:
        return len(self._rows)

    def aps(self, cell_ids: np.ndarray, grid_ids: np.ndarray, grid_xyz: np.ndarray | None = None) -> torch.Tensor:
        cell_ids, grid_ids = np.asarray(cell_ids).reshape(-1), np.asarray(grid_ids).reshape(-1)
        keys = list(zip(cell_ids.tolist(), grid_ids.tolist(), strict=True))
        todo = np.array(
            sorted({i for i, k in enumerate(keys) if k not in self._rows} - _later_duplicates(keys)), np.int64
        )
        if todo.size:
            xyz = None if grid_xyz is None else np.asarray(grid_xyz).reshape(-1, 3)[todo]
            rows = self.inner.aps(cell_ids[todo], grid_ids[todo], xyz).detach()
            self._rows.add([keys[i] for i in todo.tolist()], rows)
        return self._rows.dense(keys)

    def keep(self, other: APSCache, cell_ids: np.ndarray, grid_ids: np.ndarray) -> int:
        """Remember ``other``'s rows of these pairs (those it holds and this cache does not), without asking the
        source; returns how many.  ``other`` must wrap the same source."""
        if other.inner is not self.inner:
            raise ValueError("an APS cache keeps rows of another cache of the same source only")
        pairs = zip(np.asarray(cell_ids).reshape(-1).tolist(), np.asarray(grid_ids).reshape(-1).tolist(), strict=True)
        keys = list(dict.fromkeys(k for k in pairs if k in other._rows and k not in self._rows))
        if keys:
            self._rows.add(keys, other._rows.dense(keys))
        return len(keys)

    def level_offset_db(
        self, cell_ids: np.ndarray, beam_type: str, grid_ids: np.ndarray | None = None
    ) -> np.ndarray | None:
        return self.inner.level_offset_db(cell_ids, beam_type, grid_ids)

    def rsrp_mix(self, cell_ids: np.ndarray, grid_ids: np.ndarray, beam_type: str) -> RsrpMix | None:
        return rsrp_mix_of(self.inner, cell_ids, grid_ids, beam_type)  # no render: the wrapped source's stored table

    def round1_caps(self, cell_ids: np.ndarray, grid_ids: np.ndarray) -> np.ndarray | None:
        caps = getattr(self.inner, "round1_caps", None)
        return None if caps is None else caps(cell_ids, grid_ids)


def _later_duplicates(keys: list[tuple[int, int]]) -> set[int]:
    """Positions of keys that occur earlier in ``keys`` (computed once, by their first position)."""
    seen: set[tuple[int, int]] = set()
    later = set()
    for i, key in enumerate(keys):
        if key in seen:
            later.add(i)
        seen.add(key)
    return later


def _measured_rows(scenario: Scenario) -> list[np.ndarray]:
    """Per cell (``cell_ids()`` order), the positions in ``grid_ids()`` of its measured round-1 grids, ascending
    (one pass over the table)."""
    m = scenario.measurements
    cell_ids, grid_ids = scenario.cell_ids(), scenario.grid_ids()
    r1 = (m["round"] == 1).to_numpy()
    c = np.searchsorted(cell_ids, m["cell_id"].to_numpy()[r1])
    g = np.searchsorted(grid_ids, m["grid_id"].to_numpy()[r1])
    pairs = np.unique(c.astype(np.int64) * len(grid_ids) + g)  # sorted by cell, then grid
    bounds = np.searchsorted(pairs, np.arange(len(cell_ids) + 1, dtype=np.int64) * len(grid_ids))
    return [pairs[bounds[i] : bounds[i + 1]] - i * len(grid_ids) for i in range(len(cell_ids))]


def hearing_range_m(scenario: Scenario) -> float:
    """The farthest horizontal distance [m] between a cell's antenna and a grid where round 1 reports it, over
    every cell of the network (``inf`` when round 1 reports nothing)."""
    m = scenario.measurements
    sel = (m["round"] == 1).to_numpy() & m["rsrp_dbm"].notna().to_numpy()
    if not sel.any():
        return float("inf")
    cells, grids = scenario.cells[1], scenario.grids
    farthest = 0.0
    cell_col, grid_col = m["cell_id"].to_numpy(), m["grid_id"].to_numpy()
    for start in range(0, len(m), 4_000_000):  # bounded temporaries on a network of many millions of rows
        part = np.flatnonzero(sel[start : start + 4_000_000]) + start
        if not len(part):
            continue
        c = np.searchsorted(cells["cell_id"].to_numpy(), cell_col[part])
        g = np.searchsorted(grids["grid_id"].to_numpy(), grid_col[part])
        dx = cells["x"].to_numpy()[c] - grids["x"].to_numpy()[g]
        dy = cells["y"].to_numpy()[c] - grids["y"].to_numpy()[g]
        farthest = max(farthest, float(np.sqrt((dx * dx + dy * dy).max())))
    return farthest


def render_rows(
    source: APSSource, scenario: Scenario, free_cells: np.ndarray | None = None, measured: bool = False
) -> list[np.ndarray]:
    """Per cell (``scenario.cell_ids()`` order), the positions in ``scenario.grid_ids()`` whose APS
    :meth:`ScenarioAPS.render` renders, ascending.

    A source without unseen grids (WNOMP): the cell's measured round-1 grids.  A field model: the grids within
    :data:`REACH_MARGIN` × :func:`hearing_range_m` of the cell's antenna (horizontal distance); beyond, the pair
    counts as not heard, as WNOMP's unmeasured pairs do.  So the work grows with cells × grids in reach, linear in
    the network at a fixed density, instead of cells × all grids; on a network whose every cell is heard across
    it (the shipped one) every grid is in reach.  With ``free_cells`` (the cell ids a search may change), only
    the grids some free cell reaches are rendered, for every cell heard there: the area a change can touch.
    ``measured``: a field model too only at the measured round-1 pairs (what WNOMP always answers).
    """
    grid_ids = scenario.grid_ids()
    if measured or not source.supports_unseen_grids:
        rows = _measured_rows(scenario)
    else:
        reach = REACH_MARGIN * hearing_range_m(scenario)
        grid_xy = scenario.grids.set_index("grid_id").loc[grid_ids, ["x", "y"]].to_numpy()
        cells = scenario.cells[1].set_index("cell_id").loc[scenario.cell_ids(), ["x", "y"]].to_numpy()
        rows = []
        for x, y in cells:
            d2 = (grid_xy[:, 0] - x) ** 2 + (grid_xy[:, 1] - y) ** 2
            rows.append(np.flatnonzero(d2 <= reach * reach))
    if free_cells is None:
        return rows
    free = np.isin(scenario.cell_ids(), np.asarray(free_cells))
    area = np.zeros(len(grid_ids), dtype=bool)
    for r, is_free in zip(rows, free, strict=True):
        if is_free:
            area[r] = True
    return [r[area[r]] for r in rows]


@dataclass
class ScenarioAPS:
    """Per-cell APS on the kept bins, at the grids within reach of each cell.

    Attributes:
        cell_ids: ``[num_cells]`` sorted; grid_ids: ``[num_grids]`` sorted.
        bins: per cell, the kept flat bin indices ``[num_kept]`` of :attr:`angle_grid`.
        aps: per cell, ``[num_known, num_kept]`` float32 linear path gain at its known grids, in grid order.
        known: ``[num_cells, num_grids]`` pairs the source has an APS for (:func:`render_rows`: field models
            the grids in reach, WNOMP the measured round-1 pairs); the others count as not heard.
        angle_grid: the source's angle grid; model: the source's name.
        source_sha256: the source's key (:func:`~rflscm.models.source.source_sha256`).
        fingerprint: the fingerprint of the scenario the source was fitted for.
    """

    cell_ids: np.ndarray
    grid_ids: np.ndarray
    bins: list[np.ndarray]
    aps: list[torch.Tensor]
    known: np.ndarray
    angle_grid: AngleGrid
    model: str
    source_sha256: str = ""
    fingerprint: str | None = None
    pairs: str = ""
    """Which pairs :attr:`known` holds, in words (for reports)."""
    mix_aps: list[torch.Tensor] | None = None
    """Per cell, the source's second APS of its SSB predictions (:meth:`~rflscm.models.source.APSSource.rsrp_mix`: the
    search's beams are SSB) on the kept bins ``[num_known, num_kept]``, or ``[0, num_kept]`` where none of the cell's
    pairs has one; None: no cell has one."""
    mix_weight: list[torch.Tensor] | None = None
    """Per cell, each known pair's weight of :attr:`mix_aps` ``[num_known]`` (``[0]`` where the cell has none)."""

    def mix_of(self, pos: int) -> tuple[torch.Tensor, torch.Tensor] | None:
        """``(mix_aps, mix_weight)`` of the cell at position ``pos``, or None where it has none."""
        if self.mix_aps is None or self.mix_weight is None or not len(self.mix_weight[pos]):
            return None
        return self.mix_aps[pos], self.mix_weight[pos]

    # --- building ------------------------------------------------------------------------------------
    @classmethod
    def render(
        cls,
        source: APSSource,
        scenario: Scenario,
        chunk: int = 1024,
        on_cell: Callable[[int, int], None] | None = None,
        free_cells: np.ndarray | None = None,
        measured: bool = False,
    ) -> ScenarioAPS:
        """Render the APS of every pair within reach once (:func:`render_rows`: field models the grids within
        the network's hearing range of each cell, WNOMP the measured pairs) and keep the bins any of a cell's
        grids uses; a non-finite or negative APS is refused (:func:`~rflscm.models.source.checked_aps`).
        ``on_cell(done, total)`` after each cell; ``free_cells``: only where these cells reach, ``measured``: only
        the measured round-1 pairs (:func:`render_rows`).
        Memory: one cell's rows × all bins at a time."""
        cell_ids, grid_ids = scenario.cell_ids(), scenario.grid_ids()
        xyz_all = scenario.grids.set_index("grid_id").loc[grid_ids, ["x", "y", "z"]].to_numpy()
        known = np.zeros((len(cell_ids), len(grid_ids)), dtype=bool)
        bins, aps, mix_aps, mix_weight = [], [], [], []
        for i, (cell, rows) in enumerate(
            zip(cell_ids, render_rows(source, scenario, free_cells, measured), strict=True)
        ):
            known[i, rows] = True
            dense = torch.zeros(len(rows), source.angle_grid.num_bins)
            other, weight = torch.zeros(0, source.angle_grid.num_bins), torch.zeros(0)
            for start in range(0, len(rows), chunk):
                sel = rows[start : start + chunk]
                with torch.no_grad():
                    x = checked_aps(source, np.full(len(sel), cell), grid_ids[sel], xyz_all[sel], scenario)
                    mix = rsrp_mix_of(source, np.full(len(sel), cell), grid_ids[sel], "ssb")  # the search's beams
                dense[start : start + len(sel)] = x.detach().float().cpu()
                if mix is not None:
                    if not len(weight):
                        other, weight = torch.zeros_like(dense), torch.zeros(len(rows))
                    other[start : start + len(sel)] = mix.aps.detach().float().cpu()
                    weight[start : start + len(sel)] = mix.weight.detach().float().cpu()
            if len(rows):
                used = torch.maximum(dense.amax(dim=0), other.amax(dim=0)) if len(weight) else dense.amax(dim=0)
                keep = torch.nonzero(used > 0).reshape(-1)
            else:  # a cell with no pair to render (beyond every grid asked for)
                keep = torch.zeros(0, dtype=torch.long)
            bins.append(keep.numpy())
            aps.append(dense[:, keep].contiguous())
            mix_aps.append(other[:, keep].contiguous())
            mix_weight.append(weight)
            if on_cell is not None:
                on_cell(i + 1, len(cell_ids))
        mixed = any(len(w) for w in mix_weight)
        key = source_sha256(source)
        if measured or not source.supports_unseen_grids:
            pairs = "measured round-1 pairs only"
        else:
            pairs = "every (cell, grid) pair" if known.all() else "the (cell, grid) pairs within the model's reach"
        if free_cells is not None and len(np.unique(free_cells)) < len(cell_ids):
            pairs += ", at the grids the cells free to change reach"
        return cls(
            cell_ids,
            grid_ids,
            bins,
            aps,
            known,
            source.angle_grid,
            source.name,
            key,
            source.fingerprint,
            pairs,
            mix_aps if mixed else None,
            mix_weight if mixed else None,
        )

    # --- the file --------------------------------------------------------------------------------------
    def _payload(self) -> dict[str, Any]:
        return {
            "model": self.model,
            "source_sha256": self.source_sha256,
            "fingerprint": self.fingerprint,
            "pairs": self.pairs,
            "angle_grid": self.angle_grid.to_dict(),
            "cell_ids": torch.as_tensor(np.asarray(self.cell_ids, dtype=np.int64)),
            "grid_ids": torch.as_tensor(np.asarray(self.grid_ids, dtype=np.int64)),
            "known": torch.as_tensor(np.asarray(self.known, dtype=bool)),
            "bins": [torch.as_tensor(np.asarray(b, dtype=np.int64)) for b in self.bins],
            "aps": [a.detach().cpu().float().contiguous() for a in self.aps],
            **(
                {}
                if self.mix_aps is None or self.mix_weight is None
                else {
                    "mix_aps": [a.detach().cpu().float().contiguous() for a in self.mix_aps],
                    "mix_weight": [w.detach().cpu().float().contiguous() for w in self.mix_weight],
                }
            ),
        }

    def save(self, path: str | Path) -> Path:
        """Write the cache atomically (a unique temporary file in the same folder, fsync, rename)."""
        path = Path(path)
        if path.is_dir():
            raise APSCacheError(f"{path}: is a folder; give the APS cache a file name (e.g. {path / 'aps.pt'}).")
        path.parent.mkdir(parents=True, exist_ok=True)
        payload = self._payload()
        tmp = path.with_name(f".{path.name}.{os.getpid()}.{time.monotonic_ns()}.tmp")
        try:
            with open(tmp, "wb") as f:
                torch.save({"format": CACHE_FORMAT, "sha256": content_hash(payload), "payload": payload}, f)
                f.flush()
                os.fsync(f.fileno())
            tmp.replace(path)
        except OSError as exc:
            tmp.unlink(missing_ok=True)
            raise APSCacheError(f"{path}: cannot write the APS cache ({exc.strerror or type(exc).__name__}).") from None
        return path

    @classmethod
    def load(cls, path: str | Path, source: APSSource | None = None, scenario: Scenario | None = None) -> ScenarioAPS:
        """Read a cache written by :meth:`save` (never unpickling anything) and check it.

        With ``source``, refuse a cache written for another source (another checkpoint, retrained model or grid);
        with ``scenario``, one of another scenario or whose cells and grids differ from the scenario's.

        Raises:
            APSCacheError: not a cache file, damaged or edited, holds Python objects (refused unread), of another
                source or scenario, inconsistent shapes, or APS that are not finite and ≥ 0.
        """
        path = Path(path)
        payload = _read(path)
        try:
            cache = cls._from_payload(payload)
        except (KeyError, TypeError, ValueError, IndexError, RflscmError) as exc:
            raise APSCacheError(f"{path}: not a consistent APS cache ({type(exc).__name__}: {exc}).") from None
        cache._check(path)
        if source is not None and cache.source_sha256 != source_sha256(source):
            raise APSCacheError(
                f"{path}: this APS cache was written for another checkpoint ({cache.model}, content "
                f"{cache.source_sha256[:12]}…, this {source.name} model has {source_sha256(source)[:12]}…); delete it "
                "or give another --aps-cache path."
            )
        if scenario is not None and (
            cache.fingerprint != scenario.fingerprint()
            or not np.array_equal(cache.cell_ids, scenario.cell_ids())
            or not np.array_equal(cache.grid_ids, scenario.grid_ids())
        ):
            raise APSCacheError(
                f"{path}: this APS cache was written for another scenario than {scenario.meta.name!r} (other "
                "fingerprint, cells or grids); delete it or give another --aps-cache path."
            )
        return cache

    @classmethod
    def _from_payload(cls, p: dict[str, Any]) -> ScenarioAPS:
        def tensor(value: object, what: str) -> torch.Tensor:
            if not isinstance(value, torch.Tensor):
                raise TypeError(f"`{what}` is not a tensor")
            return value

        def tensors(value: object, what: str) -> list[torch.Tensor]:
            if not isinstance(value, list):
                raise TypeError(f"`{what}` is not a list of tensors")
            return [tensor(v, what) for v in value]

        fingerprint = p.get("fingerprint")
        return cls(
            cell_ids=tensor(p["cell_ids"], "cell_ids").numpy().astype(np.int64),
            grid_ids=tensor(p["grid_ids"], "grid_ids").numpy().astype(np.int64),
            bins=[b.numpy().astype(np.int64) for b in tensors(p["bins"], "bins")],
            aps=tensors(p["aps"], "aps"),
            known=tensor(p["known"], "known").numpy().astype(bool),
            angle_grid=AngleGrid.from_dict(p["angle_grid"]),
            model=str(p["model"]),
            source_sha256=str(p["source_sha256"]),
            fingerprint=None if fingerprint is None else str(fingerprint),
            pairs=str(p.get("pairs", "")),
            mix_aps=None if p.get("mix_aps") is None else tensors(p["mix_aps"], "mix_aps"),
            mix_weight=None if p.get("mix_weight") is None else tensors(p["mix_weight"], "mix_weight"),
        )

    def _check(self, path: Path) -> None:
        n_cells, n_grids, n_bins = len(self.cell_ids), len(self.grid_ids), self.angle_grid.num_bins
        if (
            self.known.shape != (n_cells, n_grids)
            or len(self.bins) != n_cells
            or len(self.aps) != n_cells
            or any(b.ndim != 1 or (len(b) and (b.min() < 0 or b.max() >= n_bins)) for b in self.bins)
            or any(
                a.shape != (int(k.sum()), len(b)) or not a.is_floating_point()
                for a, b, k in zip(self.aps, self.bins, self.known)
            )
        ):
            raise APSCacheError(f"{path}: not a consistent APS cache (its shapes do not fit together); delete it.")
        if (self.mix_aps is None) != (self.mix_weight is None) or (
            self.mix_aps is not None
            and self.mix_weight is not None
            and (
                len(self.mix_aps) != n_cells
                or len(self.mix_weight) != n_cells
                or any(
                    w.shape not in ((0,), (a.shape[0],))
                    or m.shape != (len(w), a.shape[1])
                    or not m.is_floating_point()
                    or not w.is_floating_point()
                    for a, m, w in zip(self.aps, self.mix_aps, self.mix_weight)
                )
            )
        ):
            raise APSCacheError(f"{path}: not a consistent APS cache (its mixed APS do not fit its APS); delete it.")
        for cell, a in zip(self.cell_ids, self.aps, strict=True):
            bad = ~torch.isfinite(a) | (a < 0)
            if bool(bad.any()):
                raise APSCacheError(
                    f"{path}: the APS cache holds non-finite or negative APS (cell {int(cell)}, {int(bad.sum())} "
                    "values); it is damaged: delete it and render the APS again."
                )
        for cell, m, w in zip(self.cell_ids, self.mix_aps or [], self.mix_weight or [], strict=False):
            if bool((~torch.isfinite(m) | (m < 0)).any()) or bool((~torch.isfinite(w) | (w < 0) | (w > 1)).any()):
                raise APSCacheError(
                    f"{path}: the APS cache holds a damaged mixed APS or weight (cell {int(cell)}); delete it and "
                    "render the APS again."
                )


def _read(path: Path) -> dict[str, Any]:
    """The verified payload of an APS cache file (``torch.load(weights_only=True)``: tensors and plain data only)."""
    if path.is_dir():
        raise APSCacheError(f"{path}: is a folder, not an APS cache file.")
    if not path.is_file():
        raise APSCacheError(f"{path}: APS cache not found (or not a regular file).")
    try:
        is_zip = is_zip_archive(path)
    except OSError as exc:
        raise APSCacheError(f"{path}: cannot read the APS cache ({exc.strerror or type(exc).__name__}).") from None
    if not is_zip:
        raise APSCacheError(f"{path}: not an rflscm APS cache (not a PyTorch archive; another kind of file).")
    try:
        archive = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        if "unsupported global" in str(exc).lower() or "unsupported class" in str(exc).lower():
            raise APSCacheError(
                f"{path}: refused: the file holds Python objects other than tensors and plain data, which could run "
                "code when loaded; rflscm APS caches never do (delete it and render the APS again)."
            ) from None
        first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
        raise APSCacheError(f"{path}: not a readable rflscm APS cache ({first}).") from None
    except Exception as exc:  # damaged archives raise anything from RuntimeError to EOFError
        first = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else type(exc).__name__
        raise APSCacheError(f"{path}: not a readable rflscm APS cache (damaged or truncated: {first}).") from None
    fmt = str(archive.get("format", "")) if isinstance(archive, dict) else ""
    if fmt.startswith("rflscm-aps-cache/") and fmt != CACHE_FORMAT:
        raise APSCacheError(
            f"{path}: an APS cache of another format ({fmt}, this rflscm reads {CACHE_FORMAT}); "
            "delete it and render the APS again."
        )
    if not isinstance(archive, dict) or archive.get("format") != CACHE_FORMAT:
        raise APSCacheError(f"{path}: not an rflscm APS cache (no `{CACHE_FORMAT}` header).")
    payload = archive.get("payload")
    if isinstance(payload, dict) and _oversized(payload):
        raise APSCacheError(
            f"{path}: refused: a tensor in the APS cache claims more elements than the file stores (a crafted "
            "stride); rflscm APS caches never do (delete it and render the APS again)."
        )
    if not isinstance(payload, dict) or archive.get("sha256") != content_hash(payload):
        raise APSCacheError(
            f"{path}: the APS cache's content does not match the SHA-256 written when it was saved (damaged or "
            "edited); delete it and render the APS again."
        )
    return payload


def _oversized(value: object) -> bool:
    """True when a tensor in ``value`` (dicts and lists of them) is larger than its storage (a stride-0 or
    overlapping view that hashing or copying would blow up to its full size)."""
    if isinstance(value, torch.Tensor):
        return value.numel() * value.element_size() > value.untyped_storage().nbytes()
    if isinstance(value, dict):
        return any(_oversized(v) for v in value.values())
    if isinstance(value, list):
        return any(_oversized(v) for v in value)
    return False


def load_or_render(
    source: APSSource,
    scenario: Scenario,
    path: str | Path | None,
    on_cell: Callable[[int, int], None] | None = None,
    free_cells: np.ndarray | None = None,
    measured: bool = False,
) -> tuple[ScenarioAPS, float]:
    """``source``'s APS of ``scenario`` (where ``free_cells`` reach, see :func:`render_rows`): read from ``path``
    when it exists (refused unless written for this very source, scenario and area, see :meth:`ScenarioAPS.load`),
    else rendered and, with ``path``, written there.  Returns the cache and the seconds it took."""
    t0 = time.perf_counter()
    if path is not None and Path(path).exists():
        cache = ScenarioAPS.load(path, source, scenario)
        expected = np.zeros_like(cache.known)
        for i, rows in enumerate(render_rows(source, scenario, free_cells, measured)):
            expected[i, rows] = True
        if not np.array_equal(cache.known, expected):
            raise APSCacheError(
                f"{path}: this APS cache was rendered for other grids ({int(cache.known.sum())} pairs, this search "
                f"needs {int(expected.sum())}: other cells free to change or other --pairs); delete it or give another "
                "--aps-cache path."
            )
        return cache, time.perf_counter() - t0
    cache = ScenarioAPS.render(source, scenario, on_cell=on_cell, free_cells=free_cells, measured=measured)
    if path is not None:
        cache.save(path)
    return cache, time.perf_counter() - t0


__all__ = [
    "CACHE_FORMAT",
    "REACH_MARGIN",
    "APSCache",
    "APSCacheError",
    "ScenarioAPS",
    "hearing_range_m",
    "load_or_render",
    "render_rows",
]
