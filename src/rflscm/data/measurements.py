"""The measurements table (long form): validation and codebook sizes.

================  =======  =========================================================
column            dtype    meaning
================  =======  =========================================================
round             int64    measurement round (a key of scenario.yaml ``rounds``)
cell_id           int64    a cell of the cells tables
grid_id           int64    a grid of the grids table
beam_type         str      ``ssb`` or ``csi`` (case and blanks ignored on input)
beam_id           int64    0-based index into the cell's codebook of that type in that round
rsrp_dbm          float64  RSRP [dBm] in −156…−31, NaN = not reported / below threshold
================  =======  =========================================================

Each (round, cell_id, grid_id, beam_type, beam_id) appears at most once.  All
checks are vectorised; a million rows validate in about a second.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pyarrow as pa  # type: ignore[import-untyped]

from rflscm.data.columns import (
    TableRef,
    check_not_empty,
    check_unknown_columns,
    clean_column_names,
    duplicate_rows,
    float_column,
    fmt_list,
    int_column,
    raise_rows,
    require_columns,
)
from rflscm.data.meta import RSRP_MAX_DBM, RSRP_MIN_DBM, ScenarioMeta
from rflscm.data.positions import finish_table
from rflscm.data.reporting import BEAM_TYPES

MEASUREMENT_COLUMNS = ("round", "cell_id", "grid_id", "beam_type", "beam_id", "rsrp_dbm")
MEASUREMENT_KEY = ["round", "cell_id", "grid_id", "beam_type", "beam_id"]
"""Beam types; index 0 / 1 in :func:`codebook_sizes`."""


def empty_measurements() -> pd.DataFrame:
    """A measurements table with the right columns and dtypes and no rows."""
    dtypes = ["int64", "int64", "int64", "str", "int64", "float64"]
    return pd.DataFrame({c: pd.Series(dtype=t) for c, t in zip(MEASUREMENT_COLUMNS, dtypes, strict=True)})


def select_rows(table: pd.DataFrame, mask: np.ndarray) -> pd.DataFrame:
    """The rows of ``table`` where ``mask [num_rows]`` holds, in order, numbered from 0.

    When they are one contiguous run (a round of a table written round by round, as every scenario rflscm writes),
    this is a slice of ``table`` that shares its columns (pandas' copy-on-write copies nothing until one of them is
    written); otherwise a copy.  At 1 002 cells round 1's rows are 1.1 GB."""
    mask = np.asarray(mask, dtype=bool)
    if mask.any():
        first, last = int(mask.argmax()), len(mask) - int(mask[::-1].argmax())
        if mask[first:last].all():
            return table.iloc[first:last].reset_index(drop=True)
    return table[mask].reset_index(drop=True)


def reported_pairs(measurements: pd.DataFrame, round: int = 1) -> pd.DataFrame:
    """The distinct (``cell_id``, ``grid_id``) pairs with at least one reported RSRP in ``round``, sorted.

    Only the two id columns of those rows are copied, never the whole rows."""
    m = measurements
    reported = (m["round"].to_numpy() == round) & ~np.isnan(m["rsrp_dbm"].to_numpy(np.float64))
    pairs = pd.DataFrame(
        {"cell_id": m["cell_id"].to_numpy()[reported], "grid_id": m["grid_id"].to_numpy()[reported]}, copy=False
    )
    return pairs.drop_duplicates().sort_values(["cell_id", "grid_id"], ignore_index=True)


def codebook_sizes(cells: dict[int, pd.DataFrame], meta: ScenarioMeta) -> np.ndarray:
    """Number of beams ``[num_rounds, num_cells, 2]`` (int64) per round (sorted), cell (sorted ids) and
    beam type (``ssb``, ``csi``)."""
    rounds = sorted(cells)
    num_beams = {name: cb.num_beams for name, cb in meta.codebooks.items()}
    sizes = np.zeros((len(rounds), len(cells[rounds[0]]), 2), dtype=np.int64)
    for i, r in enumerate(rounds):
        for t, beam_type in enumerate(BEAM_TYPES):
            sizes[i, :, t] = cells[r][f"{beam_type}_codebook"].map(num_beams).to_numpy(dtype=np.int64)
    return sizes


def normalise_measurements(
    df: pd.DataFrame,
    ref: TableRef,
    meta: ScenarioMeta,
    cells: dict[int, pd.DataFrame],
    grid_ids: np.ndarray,
    grids_name: str,
) -> pd.DataFrame:
    """Validate the measurements table against the cells (per round) and the grids.

    Args:
        df: the table as read, in file order.
        ref: its file, for messages.
        meta: scenario.yaml (round files, codebooks).
        cells: normalised cells tables by round (sorted by ``cell_id``).
        grid_ids: sorted grid ids ``[num_grids]``.
        grids_name: the grids file, for messages.

    Returns:
        The table with :data:`MEASUREMENT_COLUMNS` in their dtypes (+ extra columns), in file order.

    Memory: a column already in its dtype is kept, not copied (a Parquet file written by rflscm is: the table as
    read becomes the table returned); the positions of each row's round, cell, grid and beam type are held in the
    smallest integer type that holds them; the duplicate check sorts one packed int64 key per row instead of
    hashing.  The peak is the table plus about 20 bytes a row (issue 29, docs/scale.md).
    """
    df = clean_column_names(df, ref)
    check_not_empty(df, ref, "one row per (round, cell, grid, beam)")
    require_columns(df, ref, list(MEASUREMENT_COLUMNS))
    check_unknown_columns(df, ref, MEASUREMENT_COLUMNS)
    ids, r_idx, c_idx, g_idx = _ids(df, ref, meta, cells, grid_ids, grids_name)
    t_idx, exact = _beam_types(df, ref)
    beam_id = _beam_ids(df, ref, codebook_sizes(cells, meta), r_idx, c_idx, t_idx, cells)
    rsrp = _rsrp(df, ref)
    shape = (len(cells), len(cells[1]), len(grid_ids), 2, int(beam_id.max()) + 1)
    packed = _packed_key((r_idx, c_idx, g_idx, t_idx, beam_id), shape)
    del r_idx, c_idx, g_idx
    columns = {**ids, "beam_type": _beam_type_column(df, t_idx, exact), "beam_id": beam_id, "rsrp_dbm": rsrp}
    out = pd.DataFrame(columns, copy=False)
    fix = "each beam of a cell is measured once per grid and round (average repeated measurements before import)"
    if _has_duplicates(packed):
        duplicate_rows(ref, out, MEASUREMENT_KEY, fix, packed=packed)
    del packed
    return finish_table(out, df, None)


def _packed_key(positions: tuple[np.ndarray, ...], shape: tuple[int, ...]) -> np.ndarray:
    """One int64 ``[num_rows]`` per row, equal exactly when every position is (``np.ravel_multi_index``'s value,
    computed in place: one array of the rows' size, not one per position)."""
    key = np.asarray(positions[0], dtype=np.int64).copy()
    for pos, size in zip(positions[1:], shape[1:], strict=True):
        key *= size
        key += pos
    return key


def _has_duplicates(packed: np.ndarray) -> bool:
    """Whether two rows share a packed key (sorted copy: 8 bytes a row, against a hash table's several times)."""
    if len(packed) < 2:
        return False
    ordered = np.sort(packed)
    return bool((ordered[1:] == ordered[:-1]).any())


def _compact_index(pos: np.ndarray, size: int) -> np.ndarray:
    """``pos`` (positions < ``size``) in the smallest signed integer type that holds ``size``."""
    for dtype in (np.int8, np.int16, np.int32):
        if size <= np.iinfo(dtype).max:
            return pos.astype(dtype)
    return pos.astype(np.int64, copy=False)


def _ids(
    df: pd.DataFrame,
    ref: TableRef,
    meta: ScenarioMeta,
    cells: dict[int, pd.DataFrame],
    grid_ids: np.ndarray,
    grids_name: str,
) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray, np.ndarray]:
    """``round``, ``cell_id``, ``grid_id`` (int64 columns), and the positions ``[num_rows]`` of each row's
    round, cell and grid in the sorted rounds, cell ids and grid ids (smallest integer types)."""
    rounds = np.array(sorted(cells), dtype=np.int64)
    cell_ids = cells[1]["cell_id"].to_numpy()
    out = {c: int_column(df, ref, c) for c in ("round", "cell_id", "grid_id")}
    problem = (
        f"has no cells table; scenario.yaml `rounds` defines {fmt_list(rounds)} "
        "(add the round there with its cells file, or correct the value)"
    )
    r_idx = _index_of(out["round"], rounds, ref, "round", df, problem)
    problem = f"is not a cell of {meta.rounds[1]} (cell ids: {fmt_list(cell_ids)})"
    c_idx = _index_of(out["cell_id"], cell_ids, ref, "cell_id", df, problem)
    problem = f"is not a grid of {grids_name} (grid ids: {fmt_list(grid_ids)})"
    g_idx = _index_of(out["grid_id"], grid_ids, ref, "grid_id", df, problem)
    return out, r_idx, c_idx, g_idx


def _index_of(
    values: np.ndarray, known: np.ndarray, ref: TableRef, column: str, df: pd.DataFrame, problem: str
) -> np.ndarray:
    """Positions ``[num_rows]`` of ``values`` in the sorted ``known`` (smallest integer type); a value not in it is
    an error."""
    pos = np.searchsorted(known, values)
    np.minimum(pos, len(known) - 1, out=pos)
    raise_rows(ref, known[pos] != values, column, df[column], problem)
    return _compact_index(pos, len(known))


def _beam_types(df: pd.DataFrame, ref: TableRef) -> tuple[np.ndarray, bool]:
    """Beam-type index ``[num_rows]`` (int8: 0 = ssb, 1 = csi), and whether every value is already exactly
    ``ssb`` or ``csi``."""
    codes, uniques = pd.factorize(df["beam_type"], use_na_sentinel=True)
    lookup = np.array([_beam_type_index(u) for u in uniques] + [-1], dtype=np.int8)  # code −1 (empty) → −1
    t_idx = lookup[codes]
    problem = "is empty (NaN); every row needs `ssb` or `csi`"
    raise_rows(ref, (t_idx < 0) & (codes < 0), "beam_type", df["beam_type"], problem)
    raise_rows(ref, t_idx < 0, "beam_type", df["beam_type"], "is not one of 'ssb', 'csi'")
    exact = all(isinstance(u, str) and u in BEAM_TYPES for u in uniques)
    return t_idx, exact


_STR_DTYPE = pd.array([], dtype="str").dtype


def _beam_type_column(df: pd.DataFrame, t_idx: np.ndarray, exact: bool) -> pd.api.extensions.ExtensionArray:
    """The ``beam_type`` column (``str``): the column as read when it already holds exactly ``ssb`` / ``csi``
    (``exact``; no copy), else built from the beam-type indices through a dictionary (no object array of the rows'
    size)."""
    column = df["beam_type"]
    if exact and column.dtype == _STR_DTYPE:
        return column.array
    codes = pa.array(t_idx, type=pa.int8())
    labels = pa.DictionaryArray.from_arrays(codes, pa.array(list(BEAM_TYPES), type=pa.large_string()))
    return pd.array(labels.cast(pa.large_string()), dtype="str")


def _beam_type_index(value: object) -> int:
    text = str(value).strip().lower()
    return BEAM_TYPES.index(text) if text in BEAM_TYPES else -1


def _beam_ids(
    df: pd.DataFrame,
    ref: TableRef,
    sizes: np.ndarray,
    r_idx: np.ndarray,
    c_idx: np.ndarray,
    t_idx: np.ndarray,
    cells: dict[int, pd.DataFrame],
) -> np.ndarray:
    """``beam_id`` ``[num_rows]`` checked against the codebook size of each row's cell, round and beam type."""
    beam_id = int_column(df, ref, "beam_id")
    raise_rows(ref, beam_id < 0, "beam_id", df["beam_id"], "must be ≥ 0 (a 0-based index into the cell's codebook)")
    limit = sizes.astype(np.int32)[r_idx, c_idx, t_idx]  # [num_rows]
    too_big = beam_id >= limit
    if too_big.any():
        i = int(np.flatnonzero(too_big)[0])
        rnd = sorted(cells)[r_idx[i]]
        beam_type = BEAM_TYPES[t_idx[i]]
        cell = cells[rnd].iloc[c_idx[i]]
        name = cell[f"{beam_type}_codebook"]
        problem = (
            f"is out of range for cell {cell['cell_id']} in round {rnd}: its {beam_type} codebook {name!r} "
            f"has {limit[i]} beams (beam_id 0…{limit[i] - 1}; ids are 0-based, were they counted from 1?)"
        )
        raise_rows(ref, too_big, "beam_id", df["beam_id"], problem)
    return beam_id


def _rsrp(df: pd.DataFrame, ref: TableRef) -> np.ndarray:
    """``rsrp_dbm`` ``[num_rows]`` (NaN = missing) within the reportable range."""
    rsrp = float_column(df, ref, "rsrp_dbm", allow_nan=True, copy=False)
    span = f"the reportable range {RSRP_MIN_DBM:g}…{RSRP_MAX_DBM:g} dBm".replace("-", "−")
    problem = f"is outside {span} (values in W or mW? convert to dBm)"
    raise_rows(ref, rsrp > RSRP_MAX_DBM, "rsrp_dbm", df["rsrp_dbm"], problem)
    problem = f"is outside {span} (a missing beam is an empty value / NaN, not a sentinel such as -999)"
    raise_rows(ref, rsrp < RSRP_MIN_DBM, "rsrp_dbm", df["rsrp_dbm"], problem)
    return rsrp
