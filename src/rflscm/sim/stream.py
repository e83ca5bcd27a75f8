"""Simulation whose memory grows with a site, not with the network (issue 29).

`rflscm simulate` used to hold the whole network at once: every traced path, and the noiseless RSRP of
every (round, cell, grid, beam) as one long table (2 × cells × grids × 40 rows, 75 M rows for 37 sites,
which grows with the square of the sites).  Here:

* :class:`SpilledPaths` keeps each (site, carrier)'s trimmed paths in a file of its own as the trace goes
  (and :class:`ParquetAppender` appends them to ``truth/paths.parquet`` in row groups), so that only one
  trace is in memory;
* :func:`stream_ideal` computes, per (round, cell), the noiseless RSRP of its beams, draws the report noise
  from the same generator in the same order as :func:`rflscm.sim.noise.measure` on the whole table, keeps
  the detected pairs, and appends the truth RSRP and the true APS to their files block by block.

The files and the measurements are the ones the whole-table path wrote (same rows, same order, same
values); ``tests/unit/sim/test_stream.py`` compares both paths.
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from rflscm.data import BEAM_TYPES
from rflscm.geometry import AngleGrid
from rflscm.runtime import Mapper
from rflscm.sim.paths import (
    APS_FILE,
    COMPACT_PATHS,
    PATHS_FILE,
    RSRP_FILE,
    bin_paths,
    path_rsrp_mw,
    site_groups,
    to_dbm,
)

if TYPE_CHECKING:
    from rflscm.antenna import CellAntenna
    from rflscm.antenna.codebook import Codebook
    from rflscm.data.scenario import Scenario
    from rflscm.sim.noise import MeasurementModel

PATH_TABLE_COLUMNS = [
    "site_id",
    "freq_hz",
    "grid_id",
    "point_id",
    "power_lin",
    "aod_el_rad",
    "aod_az_rad",
    "delay_s",
    "interactions",
]
"""Columns of ``truth/paths.parquet`` in file order."""
_ROWS_PER_GROUP = 1 << 20


class ParquetAppender:
    """A zstd Parquet file written in row groups of about ``rows_per_group`` rows: frames appended one by one
    (same columns and dtypes) are buffered and flushed, so that the whole table is never in memory.  A file
    with no rows still gets the schema of ``empty`` (a frame with the columns and dtypes, no rows)."""

    def __init__(
        self, path: Path, empty: pd.DataFrame, rows_per_group: int = _ROWS_PER_GROUP, page_checksum: bool = False
    ) -> None:
        import pyarrow as pa  # type: ignore[import-untyped]
        import pyarrow.parquet as pq  # type: ignore[import-untyped]

        self.path = Path(path)
        self.rows_per_group = rows_per_group
        self._pa, self._pq = pa, pq
        self._empty = empty
        self._checksum = page_checksum
        self._writer: Any = None
        self._schema: Any = None
        self._buffer: list[pd.DataFrame] = []
        self._rows = 0
        self.num_rows = 0

    def append(self, frame: pd.DataFrame) -> None:
        if len(frame) == 0:
            return
        self._buffer.append(frame)
        self._rows += len(frame)
        self.num_rows += len(frame)
        if self._rows >= self.rows_per_group:
            self.flush()

    def _table(self, frame: pd.DataFrame):
        return self._pa.Table.from_pandas(frame, preserve_index=False)

    def flush(self) -> None:
        if not self._buffer:
            return
        if len(self._buffer) == 1:
            table = self._table(self._buffer[0])
        else:  # one table per frame (categories may differ between frames), written as one row group
            table = self._pa.concat_tables([self._table(f) for f in self._buffer], promote_options="permissive")
        if self._writer is None:
            self._schema = table.schema
            self._writer = self._pq.ParquetWriter(
                self.path, self._schema, compression="zstd", write_page_checksum=self._checksum
            )
        self._writer.write_table(table.unify_dictionaries().combine_chunks().cast(self._schema))
        self._buffer, self._rows = [], 0

    def close(self) -> None:
        self.flush()
        if self._writer is None:  # no rows at all: the schema of the empty frame
            self._empty.to_parquet(self.path, index=False, compression="zstd", write_page_checksum=self._checksum)
            return
        self._writer.close()

    def __enter__(self) -> ParquetAppender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def compact_paths(table: pd.DataFrame) -> pd.DataFrame:
    """A path table in the columns and dtypes of ``truth/paths.parquet``."""
    return table[PATH_TABLE_COLUMNS].astype({**COMPACT_PATHS, "interactions": "category"})


class PathStore:
    """The traced paths of a network by (``site_id``, ``freq_hz``), one group at a time."""

    def group_keys(self) -> list[tuple[int, float]]:
        raise NotImplementedError

    def group(self, key: tuple[int, float]) -> pd.DataFrame | None:
        """The paths of one (site, carrier) (``None``: never traced)."""
        raise NotImplementedError

    @property
    def num_rows(self) -> int:
        raise NotImplementedError

    def frame(self) -> pd.DataFrame:
        """Every path as one table (the whole network in memory: only where a step needs it at once)."""
        groups = [g for key in self.group_keys() if (g := self.group(key)) is not None]
        if not groups:
            from rflscm.sim.backend import empty_path_table

            return empty_path_table()
        return pd.concat(groups, ignore_index=True)


class MemoryPaths(PathStore):
    """A path table already in memory, seen by group."""

    def __init__(self, paths: pd.DataFrame) -> None:
        self.paths = paths
        self._groups = site_groups(paths)

    def group_keys(self) -> list[tuple[int, float]]:
        return list(self._groups)

    def group(self, key: tuple[int, float]) -> pd.DataFrame | None:
        return self._groups.get(key)

    @property
    def num_rows(self) -> int:
        return len(self.paths)

    def frame(self) -> pd.DataFrame:
        return self.paths


class SpilledPaths(PathStore):
    """Groups kept in a folder (one pickle per (site, carrier): exact dtypes and values), read back on demand;
    the last group read is cached.  :meth:`remove` deletes the folder."""

    def __init__(self, folder: Path) -> None:
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self._files: dict[tuple[int, float], Path] = {}
        self._rows = 0
        self._cached: tuple[tuple[int, float], pd.DataFrame] | None = None

    def add(self, site_id: int, freq_hz: float, table: pd.DataFrame) -> None:
        key = (int(site_id), float(freq_hz))
        path = self.folder / f"{len(self._files):06d}.pkl"
        table.to_pickle(path)
        self._files[key] = path
        self._rows += len(table)

    def group_keys(self) -> list[tuple[int, float]]:
        return list(self._files)  # in the order added (the trace's)

    def group(self, key: tuple[int, float]) -> pd.DataFrame | None:
        key = (int(key[0]), float(key[1]))
        if self._cached is not None and self._cached[0] == key:
            return self._cached[1]
        path = self._files.get(key)
        if path is None:
            return None
        table = pd.read_pickle(path)
        self._cached = (key, table)
        return table

    @property
    def num_rows(self) -> int:
        return self._rows

    def remove(self) -> None:
        self._cached = None
        shutil.rmtree(self.folder, ignore_errors=True)


def _cells_in_order(scenario: Scenario, rnd: int) -> Iterator[tuple[int, pd.Series, tuple[int, float]]]:
    for cell_id in scenario.cell_ids():
        row = scenario.cell_row(int(cell_id), rnd)
        yield int(cell_id), row, (int(row["site_id"]), float(row["freq_hz"]))


def write_aps_streamed(
    path: Path, scenario: Scenario, store: PathStore, angle_grid: AngleGrid, points_per_grid: pd.Series | int
) -> int:
    """``truth/aps.parquet`` cell by cell (what :func:`rflscm.sim.paths.true_aps_table` builds whole): the rows
    of each cell (ascending ``cell_id``) are its (site, carrier)'s paths binned once, sorted by (grid, bin).
    Returns the number of rows."""
    empty = pd.DataFrame(
        {
            "cell_id": pd.Series(dtype="int32"),
            "grid_id": pd.Series(dtype="int32"),
            "bin": pd.Series(dtype="int32"),
            "power_lin": pd.Series(dtype="float64"),
        }
    )
    binned: tuple[tuple[int, float], pd.DataFrame] | None = None
    with ParquetAppender(path, empty) as out:
        for cell_id, _, key in _cells_in_order(scenario, 1):
            sub = store.group(key)
            if sub is None:
                continue
            if binned is None or binned[0] != key:
                binned = (key, bin_paths(sub, angle_grid, points_per_grid))
            aps = binned[1]
            out.append(
                pd.DataFrame(
                    {
                        "cell_id": np.full(len(aps), cell_id, dtype=np.int32),
                        "grid_id": aps["grid_id"].to_numpy().astype(np.int32),
                        "bin": aps["bin"].to_numpy(np.int32),
                        "power_lin": aps["power_lin"].to_numpy(np.float64),
                    }
                )
            )
        return out.num_rows


def long_rows(rnd: int, cell_id: int, blocks: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, np.ndarray]:
    """Long-form columns of one (round, cell) from ``(grid ids [n], values [n, beams])`` of the SSB and then the
    CSI-RS block (``BEAM_TYPES`` order): grid-major within a block, every beam of a listed grid — the rows
    :func:`rflscm.sim.paths.noiseless_rsrp` lists for those grids, in its order."""
    parts: dict[str, list[np.ndarray]] = {"grid_id": [], "beam_type": [], "beam_id": [], "rsrp_dbm": []}
    for t, (grids, values) in enumerate(blocks):
        n, num_beams = values.shape
        parts["grid_id"].append(np.repeat(grids, num_beams))
        parts["beam_type"].append(np.full(n * num_beams, t, dtype=np.int8))
        parts["beam_id"].append(np.tile(np.arange(num_beams, dtype=np.int64), n))
        parts["rsrp_dbm"].append(values.reshape(-1))
    cols = {k: np.concatenate(v) for k, v in parts.items()}
    num = len(cols["grid_id"])
    return {"round": np.full(num, rnd, dtype=np.int64), "cell_id": np.full(num, cell_id, dtype=np.int64), **cols}


def _rsrp_rows(
    rsrp_dbm: dict[str, np.ndarray], keep: np.ndarray, rnd: int, cell_id: int, grid_ids: np.ndarray
) -> dict[str, np.ndarray]:
    """:func:`long_rows` of one (round, cell)'s ``[grids, beams]`` values by beam type at the grids ``keep``."""
    return long_rows(rnd, cell_id, [(grid_ids[keep], rsrp_dbm[bt][keep]) for bt in BEAM_TYPES])


def empty_truth_rsrp() -> pd.DataFrame:
    """``truth/rsrp_noiseless.parquet``'s columns and dtypes, no rows."""
    return pd.DataFrame(
        {
            "round": pd.Series(dtype="int8"),
            "cell_id": pd.Series(dtype="int32"),
            "grid_id": pd.Series(dtype="int32"),
            "beam_type": pd.Categorical([], categories=sorted(BEAM_TYPES)),
            "beam_id": pd.Series(dtype="int16"),
            "rsrp_dbm": pd.Series(dtype="float32"),
        }
    )


def truth_rsrp_frame(rows: dict[str, np.ndarray]) -> pd.DataFrame:
    """:func:`long_rows` in the columns of ``truth/rsrp_noiseless.parquet`` (RSRP rounded to 0.01 dB, float32)."""
    return pd.DataFrame(
        {
            "round": rows["round"].astype(np.int8),
            "cell_id": rows["cell_id"].astype(np.int32),
            "grid_id": rows["grid_id"].astype(np.int32),
            "beam_type": pd.Categorical.from_codes(_category_codes(rows["beam_type"]), categories=sorted(BEAM_TYPES)),
            "beam_id": rows["beam_id"].astype(np.int16),
            "rsrp_dbm": np.round(rows["rsrp_dbm"], 2).astype(np.float32),
        }
    )


@dataclass(frozen=True)
class RsrpJob:
    """One (site, carrier)'s cells in one round, for :func:`group_rsrp`: per cell ``(cell_id, antenna, codebooks by
    beam type, wavelength [m])``, in ascending cell id, and the (site, carrier)'s traced ``paths``."""

    round: int
    cells: tuple[tuple[int, CellAntenna, dict[str, Codebook], float], ...]
    paths: pd.DataFrame


def rsrp_jobs(scenario: Scenario, store: PathStore) -> Iterator[RsrpJob]:
    """The jobs of :func:`stream_ideal`, round by round, cells in ascending id grouped by (site, carrier) as they
    come (the cell ids of a site and carrier are consecutive), each group's paths read when its job is drawn."""
    for rnd in scenario.rounds():
        group: list[tuple[int, CellAntenna, dict[str, Codebook], float]] = []
        group_key: tuple[int, float] | None = None
        for cell_id, _, key in _cells_in_order(scenario, rnd):
            if group and key != group_key:
                yield RsrpJob(rnd, tuple(group), _paths_of(store, group_key))
                group = []
            group_key = key
            books = {bt: scenario.codebook(cell_id, bt, rnd) for bt in BEAM_TYPES}
            group.append((cell_id, scenario.antenna(cell_id, rnd), books, scenario.wavelength_m(cell_id)))
        if group:
            yield RsrpJob(rnd, tuple(group), _paths_of(store, group_key))


def _paths_of(store: PathStore, key: tuple[int, float] | None) -> pd.DataFrame:
    """The paths of ``key``, or no rows (in the store's columns) where that (site, carrier) was never traced."""
    sub = None if key is None else store.group(key)
    if sub is not None:
        return sub
    for other in store.group_keys():  # the columns and dtypes of a traced group
        found = store.group(other)
        if found is not None:
            return found.iloc[:0]
    from rflscm.sim.backend import empty_path_table

    return empty_path_table()


def group_rsrp(
    grid_ids: np.ndarray, counts: pd.Series, job: RsrpJob
) -> tuple[int, list[tuple[int, dict[str, np.ndarray]]]]:
    """``(round, [(cell_id, noiseless RSRP [dBm] [grids, beams] by beam type), …])`` of ``job``'s cells at
    ``grid_ids`` (:func:`rflscm.sim.paths.path_rsrp_mw` through each cell's antenna and codebooks)."""
    out = []
    for cell_id, antenna, books, wavelength in job.cells:
        out.append(
            (
                cell_id,
                {bt: to_dbm(path_rsrp_mw(job.paths, antenna, books[bt], wavelength, grid_ids, counts)) for bt in books},
            )
        )
    return job.round, out


def stream_ideal(
    scenario: Scenario,
    store: PathStore,
    points_per_grid: int,
    model: MeasurementModel,
    rng: np.random.Generator,
    detect_on: str | None,
    truth: Path,
    rsrp_floor_dbm: float | None,
    angle_grid: AngleGrid,
    measurements_file: Path | None = None,
    mapper: Mapper = map,
) -> pd.DataFrame:
    """The ideal regime's measurements and ``truth/`` (APS and noiseless RSRP), one (round, cell) at a time.

    Equal to :func:`rflscm.sim.paths.noiseless_rsrp` → :func:`rflscm.sim.noise.measure` →
    :func:`rflscm.sim.paths.write_truth` on whole tables (the report noise is drawn from ``rng`` block by
    block in the whole table's row order, which gives the same numbers), but only one cell's RSRP
    (grids × beams) is in memory besides the measurements that are kept.  A round-2 cell equal to its
    round-1 row is computed again from the same paths (the same numbers).  ``truth/paths.parquet`` is not
    written here (the trace appends it).  Returns the measurements table; with ``measurements_file`` the
    table is appended to that Parquet file block by block instead (page checksums, as
    :func:`rflscm.data.io.write_table` writes) and the table returned is empty.  ``mapper`` runs the noiseless
    RSRP of each (site, carrier, round) (:func:`group_rsrp`; Ray workers with :func:`rflscm.parallel.work.mapper`);
    the report noise is drawn here, in order, so the numbers do not depend on it.
    """
    from rflscm.data import empty_measurements

    grid_ids = np.asarray(scenario.grid_ids())
    counts = pd.Series(points_per_grid, index=grid_ids)
    truth.mkdir(parents=True, exist_ok=True)
    write_aps_streamed(truth / APS_FILE, scenario, store, angle_grid, counts)
    detect_t = None if detect_on is None else BEAM_TYPES.index(detect_on)
    kept: list[dict[str, np.ndarray]] = []
    sink = None
    if measurements_file is not None:
        sink = ParquetAppender(measurements_file, empty_measurements(), page_checksum=True)
    with ParquetAppender(truth / RSRP_FILE, empty_truth_rsrp()) as rsrp_file:
        for rnd, cells in mapper(partial(group_rsrp, grid_ids, counts), rsrp_jobs(scenario, store)):
            for cell_id, noiseless in cells:
                reported = {bt: model.apply(noiseless[bt], rng) for bt in BEAM_TYPES}  # draws in table order
                heard = [~np.isnan(reported[bt]).all(axis=1) for bt in BEAM_TYPES]  # [grids] per type
                detected = heard[detect_t] if detect_t is not None else heard[0] | heard[1]
                if detected.any():
                    kept.append(_rsrp_rows(reported, detected, rnd, cell_id, grid_ids))
                    if sink is not None:
                        sink.append(_measurement_frame(kept))
                        kept = []
                keep_truth = np.ones(len(grid_ids), dtype=bool)
                if rsrp_floor_dbm is not None:
                    best = np.maximum(noiseless[BEAM_TYPES[0]].max(axis=1), noiseless[BEAM_TYPES[1]].max(axis=1))
                    keep_truth = best >= rsrp_floor_dbm
                if keep_truth.any():
                    rsrp_file.append(truth_rsrp_frame(_rsrp_rows(noiseless, keep_truth, rnd, cell_id, grid_ids)))
    if sink is not None:
        sink.close()
        return empty_measurements()
    return _measurement_frame(kept)


def _category_codes(type_index: np.ndarray) -> np.ndarray:
    """Codes in ``sorted(BEAM_TYPES)`` of beam-type indices into ``BEAM_TYPES``."""
    order = sorted(BEAM_TYPES)
    lookup = np.array([order.index(bt) for bt in BEAM_TYPES], dtype=np.int8)
    return lookup[type_index]


def _measurement_frame(blocks: list[dict[str, np.ndarray]]) -> pd.DataFrame:
    """The measurements table (``round``, ``cell_id``, ``grid_id``, ``beam_type``, ``beam_id``, ``rsrp_dbm``)
    of the kept blocks, in their order."""
    from rflscm.data import empty_measurements

    if not blocks:
        return empty_measurements()
    cols = {k: np.concatenate([b[k] for b in blocks]) for k in blocks[0]}
    beam_type = np.asarray(BEAM_TYPES, dtype=object)[cols.pop("beam_type")]
    return pd.DataFrame(
        {
            "round": cols["round"],
            "cell_id": cols["cell_id"],
            "grid_id": cols["grid_id"].astype(np.int64),
            "beam_type": pd.array(beam_type, dtype="str"),
            "beam_id": cols["beam_id"],
            "rsrp_dbm": cols["rsrp_dbm"],
        }
    )


__all__ = [
    "PATHS_FILE",
    "MemoryPaths",
    "ParquetAppender",
    "PathStore",
    "SpilledPaths",
    "compact_paths",
    "stream_ideal",
    "write_aps_streamed",
]
