"""Positions in tables (x/y/z or lat/lon/height_m) and the grids table.

A table gives positions either as ``x``, ``y``, ``z`` [m] in the scenario's
ENU frame or as ``lat``, ``lon`` [deg] and ``height_m`` [m], projected with
:mod:`rflscm.data.geo` around ``scenario.yaml``'s ``origin``.  Normalised tables
always carry ``x``, ``y``, ``z`` and no geographic columns.
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
    int_column,
    raise_rows,
    require_columns,
)
from rflscm.data.geo import Origin, geodetic_to_enu
from rflscm.data.plausibility import (
    COORDINATE_FIX,
    HEIGHT_FIX,
    HEIGHT_RANGE_M,
    MAX_HORIZONTAL_M,
    height_problem,
    horizontal_problem,
)
from rflscm.data.terrain import Terrain
from rflscm.errors import DataError

XYZ = ("x", "y", "z")
GEO = ("lat", "lon", "height_m")
POSITION_TEXT = "x, y, z [m] (or lat, lon, height_m with an `origin` in scenario.yaml)"
MAX_GEO_DISTANCE_M = 200e3
"""Projected points farther than this from the origin are reported (swapped lat/lon, wrong origin)."""

GRID_COLUMNS = ("grid_id", "x", "y", "z")


def position_columns(
    df: pd.DataFrame, ref: TableRef, required: list[str], origin: Origin | None, terrain: Terrain | None = None
) -> np.ndarray:
    """ENU positions ``[num_rows, 3]`` [m] of a table's rows.

    ``required`` are the table's other required columns (for the missing-column message).  With a
    ``terrain``, ``height_m`` is above ground: z = terrain(x, y) + height_m − origin.height_m.
    """
    has_xyz = any(c in df.columns for c in XYZ)
    has_geo = any(c in df.columns for c in GEO)
    if has_xyz and has_geo:
        raise DataError(
            f"{ref.name}: gives both x/y/z and lat/lon/height_m columns; keep one set of coordinates "
            "(metres in the scenario frame, or geographic with an `origin`)."
        )
    if not has_geo:
        require_columns(df, ref, list(required[:1]) + list(XYZ) + list(required[1:]), _required_text(required))
        xyz = np.stack([float_column(df, ref, c) for c in XYZ], axis=-1)
        _plausible(df, ref, xyz, geo=False)
        return xyz
    require_columns(df, ref, list(required[:1]) + list(GEO) + list(required[1:]), _required_text(required))
    if origin is None:
        raise DataError(
            f"{ref.name}: gives lat/lon/height_m but scenario.yaml has no `origin`; add "
            "`origin: {lat: …, lon: …, height_m: 0}` (the centre of the local frame) or give x/y/z in metres."
        )
    xyz = _project(df, ref, origin)
    if terrain is not None:
        ground = terrain.elevation(xyz[:, :2])
        problem = f"puts the point outside the terrain {terrain.name!r} (or on a nodata cell); extend the DEM"
        raise_rows(ref, ~np.isfinite(ground), "lat", df["lat"], problem)
        xyz[:, 2] += ground  # height_m above ground; geodetic_to_enu already subtracted origin.height_m
    _plausible(df, ref, xyz, geo=True)
    return xyz


def _plausible(df: pd.DataFrame, ref: TableRef, xyz: np.ndarray, geo: bool) -> None:
    """Per-row coordinate limits of :mod:`rflscm.data.plausibility`."""
    far = horizontal_problem(xyz)
    if far.any():
        column = "lat" if geo else ("x" if np.abs(xyz[np.flatnonzero(far)[0], 0]) > MAX_HORIZONTAL_M else "y")
        raise_rows(
            ref,
            far,
            column,
            df[column],
            f"puts the point more than {MAX_HORIZONTAL_M / 1e3:g} km from the frame's origin; {COORDINATE_FIX}",
        )
    column = "height_m" if geo else "z"
    lo, hi = HEIGHT_RANGE_M
    problem = f"is outside the plausible {lo:g}…{hi:g} m; {HEIGHT_FIX}"
    raise_rows(ref, height_problem(xyz), column, df[column], problem)


def _required_text(required: list[str]) -> str:
    return ", ".join([*required[:1], POSITION_TEXT, *required[1:]])


def _project(df: pd.DataFrame, ref: TableRef, origin: Origin) -> np.ndarray:
    lat, lon, height = (float_column(df, ref, c) for c in GEO)
    raise_rows(ref, np.abs(lat) > 90, "lat", df["lat"], "must lie in −90…90° (degrees north)")
    raise_rows(ref, np.abs(lon) > 180, "lon", df["lon"], "must lie in −180…180° (east positive)")
    xyz = geodetic_to_enu(lat, lon, height, origin)
    far = np.hypot(xyz[:, 0], xyz[:, 1]) > MAX_GEO_DISTANCE_M
    raise_rows(
        ref,
        far,
        "lat",
        df["lat"],
        f"puts the point more than {MAX_GEO_DISTANCE_M / 1e3:.0f} km from the origin "
        f"({origin.lat}, {origin.lon}); are lat and lon swapped, or is `origin` wrong?",
    )
    return xyz


def normalise_grids(
    df: pd.DataFrame, ref: TableRef, origin: Origin | None, terrain: Terrain | None = None
) -> pd.DataFrame:
    """Validate the grids table; returns ``grid_id`` (int64), ``x``, ``y``, ``z`` (float64, m) + extra columns,
    sorted by ``grid_id`` with a 0…n−1 index."""
    df = clean_column_names(df, ref)
    check_not_empty(df, ref, "one row per grid: grid_id and the grid centre's position")
    require_columns(df, ref, ["grid_id"], "grid_id, " + POSITION_TEXT)
    xyz = position_columns(df, ref, ["grid_id"], origin, terrain)
    check_unknown_columns(df, ref, known_columns(df, GRID_COLUMNS))
    out = pd.DataFrame({"grid_id": int_column(df, ref, "grid_id")})
    out[list(XYZ)] = xyz
    duplicate_rows(ref, out, ["grid_id"], "every grid needs its own id")
    return finish_table(out, df, ["grid_id"])


def known_columns(df: pd.DataFrame, columns: tuple[str, ...]) -> list[str]:
    """``columns`` of a normalised table with x/y/z replaced by lat/lon/height_m when ``df`` is geographic."""
    if any(c in df.columns for c in GEO):
        return [c for c in columns if c not in XYZ] + list(GEO)
    return list(columns)


def finish_table(out: pd.DataFrame, raw: pd.DataFrame, sort_by: list[str] | None) -> pd.DataFrame:
    """Append the raw table's extra columns (kept as is), sort by ``sort_by`` (stable) and reset the index."""
    dropped = set(GEO) | set(out.columns)
    for column in raw.columns:
        if column not in dropped:
            out[column] = raw[column].array  # positional, dtype kept
    if sort_by:
        out = out.sort_values(sort_by, kind="stable")
    return out.reset_index(drop=True)
