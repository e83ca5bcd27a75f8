"""Terrain in an import: antenna and UE heights above ground become z in the scenario frame.

With ``terrain:`` (``--terrain``: a DEM GeoTIFF or an XYZ table, :mod:`rflscm.data.terrain`), a cell's
``height_m`` and a sample's ``height_m`` (or ``ue_height_m``) are above the ground under them:
z = terrain(x, y) + height − origin.height_m, as ``rflscm check`` places ``lat/lon/height_m`` rows.  The
importer writes x/y/z tables, so the scenario keeps those positions; the terrain file is copied in and named
in scenario.yaml (``terrain:``) to record where the heights came from.  A cell outside the terrain stops the
import naming it; samples outside it (or on nodata) are dropped and counted.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from rflscm.data.geo import Origin
from rflscm.data.ingest.samples import Tally
from rflscm.data.terrain import Terrain, load_terrain
from rflscm.errors import DataError

OUTSIDE = "outside the terrain (or on a nodata cell)"


def read_terrain(path: str, origin: Origin | None) -> Terrain:
    """The terrain file ``path`` (errors: one line naming it)."""
    p = Path(path)
    return load_terrain(p.parent, p.name, origin)


def lift(xy: np.ndarray, terrain: Terrain, origin: Origin | None) -> np.ndarray:
    """Ground [m] under ``xy [n, 2]`` relative to the frame's z = 0 (the origin's height); NaN outside."""
    return terrain.elevation(xy) - (origin.height_m if origin is not None else 0.0)


def cells_on_ground(cells: pd.DataFrame, terrain: Terrain, origin: Origin | None, file: str) -> pd.DataFrame:
    """``cells`` with z = ground + height_m; a cell outside the terrain is a :class:`DataError` naming it."""
    ground = lift(cells[["x", "y"]].to_numpy(np.float64), terrain, origin)
    bad = ~np.isfinite(ground)
    if bad.any():
        row = cells[bad].iloc[0]
        raise DataError(
            f"{file}: cell {row['cell_name']!r} at x = {row['x']:.1f}, y = {row['y']:.1f} m lies outside the terrain "
            f"{terrain.name!r} (or on a nodata cell); extend the DEM ({int(bad.sum())} cell(s) in all)."
        )
    return cells.assign(z=cells["z"].to_numpy() + ground)


def samples_on_ground(samples: pd.DataFrame, terrain: Terrain, origin: Origin | None, tally: Tally) -> pd.DataFrame:
    """``samples`` with z raised by the ground; samples outside the terrain dropped and counted."""
    ground = lift(samples[["x", "y"]].to_numpy(np.float64), terrain, origin)
    bad = ~np.isfinite(ground)
    tally.drop(f"{terrain.name}: {OUTSIDE}", int(bad.sum()))
    return samples.assign(z=samples["z"].to_numpy() + ground)[~bad].reset_index(drop=True)
