"""Facts about a scenario for ``rflscm check`` and reports (no printing here)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from rflscm.data.cells import CELL_COLUMNS
from rflscm.data.measurements import BEAM_TYPES, MEASUREMENT_COLUMNS
from rflscm.data.positions import GRID_COLUMNS
from rflscm.data.scenario import Scenario


def cells_per_carrier(scenario: Scenario) -> dict[float, int]:
    """Number of cells per carrier [Hz] (round 1), ascending carrier."""
    counts = scenario.cells[1]["freq_hz"].value_counts()
    return {float(f): int(counts[f]) for f in sorted(counts.index)}


def measurement_stats(scenario: Scenario) -> pd.DataFrame:
    """One row per (round, beam_type) present.

    Columns: ``round``, ``beam_type``, ``rows``, ``pairs`` ((cell, grid) pairs), ``cells``, ``grids``,
    ``missing`` (fraction of rows with NaN RSRP), ``below_threshold`` (reported values under r_th).
    """
    m = scenario.measurements
    columns = ["round", "beam_type", "rows", "pairs", "cells", "grids", "missing", "below_threshold"]
    if len(m) == 0:
        return pd.DataFrame(columns=columns)
    # Per (round, beam type), on numpy columns and sorted unique counts: no copy of the table, no hash of its rows.
    rounds, rsrp = m["round"].to_numpy(), m["rsrp_dbm"].to_numpy()
    cells, grids = m["cell_id"].to_numpy(), m["grid_id"].to_numpy()
    grid_span = int(grids.max()) + 1
    out = []
    for rnd in np.unique(rounds):
        in_round = rounds == rnd
        for beam_type in BEAM_TYPES:
            sel = in_round & (m["beam_type"] == beam_type).to_numpy()
            rows = int(sel.sum())
            if not rows:
                continue
            c, g, r = cells[sel], grids[sel], rsrp[sel]
            missing = np.isnan(r)
            out.append(
                {
                    "round": rnd,
                    "beam_type": beam_type,
                    "rows": rows,
                    "pairs": len(np.unique(c * grid_span + g)),
                    "cells": len(np.unique(c)),
                    "grids": len(np.unique(g)),
                    "missing": int(missing.sum()) / rows,
                    "below_threshold": int((r < scenario.meta.rsrp_threshold_dbm).sum()),
                }
            )
    stats = pd.DataFrame(out, columns=columns)
    stats["beam_type"] = stats["beam_type"].astype(str)
    return stats


def table_rows(scenario: Scenario) -> dict[str, int]:
    """Rows read per table file (file name as in scenario.yaml → rows); every row of a file that loads is read."""
    meta = scenario.meta
    rows = {name: len(scenario.cells[r]) for r, name in meta.rounds.items()}
    rows[meta.grids] = len(scenario.grids)
    if meta.measurements is not None:
        rows[meta.measurements] = len(scenario.measurements)
    return rows


def ignored_columns(scenario: Scenario) -> dict[str, list[str]]:
    """Columns of each table file that rflscm does not use (kept in the tables, but ignored)."""
    meta = scenario.meta
    tables = [(meta.rounds[r], df, CELL_COLUMNS) for r, df in scenario.cells.items()]
    tables.append((meta.grids, scenario.grids, GRID_COLUMNS))
    if meta.measurements is not None:
        tables.append((meta.measurements, scenario.measurements, MEASUREMENT_COLUMNS))
    out = {}
    for name, df, known in tables:
        extra = [str(c) for c in df.columns if c not in known]
        if extra:
            out[name] = extra
    return out


def notes(scenario: Scenario) -> list[str]:
    """Things worth knowing that are not errors (unused columns, cells or grids without data, values under r_th)."""
    out = [
        f"{name}: column(s) {', '.join(f'`{c}`' for c in columns)} are not used by rflscm (ignored)"
        for name, columns in ignored_columns(scenario).items()
    ]
    m = scenario.measurements
    if len(m) == 0:
        return [*out, "no measurements: usable for predictions only"]
    round1 = m[(m["round"] == 1).to_numpy()]
    silent = np.setdiff1d(scenario.cell_ids(), round1["cell_id"].unique())
    if silent.size:
        out.append(f"{silent.size} cell(s) have no round-1 measurements: {', '.join(map(str, silent[:10]))}")
    empty_grids = np.setdiff1d(scenario.grid_ids(), m["grid_id"].unique())
    if empty_grids.size:
        out.append(f"{empty_grids.size} grid(s) have no measurements (predictions only)")
    below = int((m["rsrp_dbm"] < scenario.meta.rsrp_threshold_dbm).sum())
    if below:
        out.append(
            f"{below} reported value(s) lie below rsrp_threshold_dbm = {scenario.meta.rsrp_threshold_dbm:g} dBm; "
            "is the threshold right?"
        )
    return out
