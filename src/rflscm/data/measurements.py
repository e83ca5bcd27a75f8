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
    """
    df = clean_column_names(df, ref)
    check_not_empty(df, ref, "one row per (round, cell, grid, beam)")
    require_columns(df, ref, list(MEASUREMENT_COLUMNS))
    check_unknown_columns(df, ref, MEASUREMENT_COLUMNS)
    out, r_idx, c_idx, g_idx = _ids(df, ref, meta, cells, grid_ids, grids_name)
    t_idx = _beam_types(df, ref)
    out["beam_type"] = pd.array(np.asarray(BEAM_TYPES, dtype=object)[t_idx], dtype="str")
    out["beam_id"] = _beam_ids(df, ref, codebook_sizes(cells, meta), r_idx, c_idx, t_idx, cells)
    out["rsrp_dbm"] = _rsrp(df, ref)
    shape = (len(cells), len(cells[1]), len(grid_ids), 2, int(out["beam_id"].max()) + 1)
    packed = np.ravel_multi_index((r_idx, c_idx, g_idx, t_idx, out["beam_id"].to_numpy()), shape)
    fix = "each beam of a cell is measured once per grid and round (average repeated measurements before import)"
    duplicate_rows(ref, out, MEASUREMENT_KEY, fix, packed=packed)
    return finish_table(out, df, None)


def _ids(
    df: pd.DataFrame,
    ref: TableRef,
    meta: ScenarioMeta,
    cells: dict[int, pd.DataFrame],
    grid_ids: np.ndarray,
    grids_name: str,
) -> tuple[pd.DataFrame, np.ndarray, np.ndarray, np.ndarray]:
    """``round``, ``cell_id``, ``grid_id`` as a new table, and the positions ``[num_rows]`` of each row's
    round, cell and grid in the sorted rounds, cell ids and grid ids."""
    rounds = np.array(sorted(cells), dtype=np.int64)
    cell_ids = cells[1]["cell_id"].to_numpy()
    out = pd.DataFrame({c: int_column(df, ref, c) for c in ("round", "cell_id", "grid_id")})
    problem = (
        f"has no cells table; scenario.yaml `rounds` defines {fmt_list(rounds)} "
        "(add the round there with its cells file, or correct the value)"
    )
    r_idx = _index_of(out["round"].to_numpy(), rounds, ref, "round", df, problem)
    problem = f"is not a cell of {meta.rounds[1]} (cell ids: {fmt_list(cell_ids)})"
    c_idx = _index_of(out["cell_id"].to_numpy(), cell_ids, ref, "cell_id", df, problem)
    problem = f"is not a grid of {grids_name} (grid ids: {fmt_list(grid_ids)})"
    g_idx = _index_of(out["grid_id"].to_numpy(), grid_ids, ref, "grid_id", df, problem)
    return out, r_idx, c_idx, g_idx


def _index_of(
    values: np.ndarray, known: np.ndarray, ref: TableRef, column: str, df: pd.DataFrame, problem: str
) -> np.ndarray:
    """Positions ``[num_rows]`` of ``values`` in the sorted ``known``; a value not in it is an error."""
    pos = np.clip(np.searchsorted(known, values), 0, len(known) - 1)
    raise_rows(ref, known[pos] != values, column, df[column], problem)
    return pos


def _beam_types(df: pd.DataFrame, ref: TableRef) -> np.ndarray:
    """Beam-type index ``[num_rows]`` (0 = ssb, 1 = csi)."""
    codes, uniques = pd.factorize(df["beam_type"], use_na_sentinel=True)
    lookup = np.array([_beam_type_index(u) for u in uniques] + [-1], dtype=np.int64)  # code −1 (empty) → −1
    t_idx = lookup[codes]
    problem = "is empty (NaN); every row needs `ssb` or `csi`"
    raise_rows(ref, (t_idx < 0) & (codes < 0), "beam_type", df["beam_type"], problem)
    raise_rows(ref, t_idx < 0, "beam_type", df["beam_type"], "is not one of 'ssb', 'csi'")
    return t_idx


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
    limit = sizes[r_idx, c_idx, t_idx]  # [num_rows]
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
    rsrp = float_column(df, ref, "rsrp_dbm", allow_nan=True)
    span = f"the reportable range {RSRP_MIN_DBM:g}…{RSRP_MAX_DBM:g} dBm".replace("-", "−")
    problem = f"is outside {span} (values in W or mW? convert to dBm)"
    raise_rows(ref, rsrp > RSRP_MAX_DBM, "rsrp_dbm", df["rsrp_dbm"], problem)
    problem = f"is outside {span} (a missing beam is an empty value / NaN, not a sentinel such as -999)"
    raise_rows(ref, rsrp < RSRP_MIN_DBM, "rsrp_dbm", df["rsrp_dbm"], problem)
    return rsrp
