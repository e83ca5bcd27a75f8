"""The building point cloud of an import: read and validated as ``rflscm check`` reads it, then checked against the
imported grids, because the importer cannot move it: the cloud must already be in the scenario's local frame.

The frame is the one the samples and cells are projected to: x east, y north [m] from the import's origin
(``origin:`` / ``--origin``, else the centroid of the cells), z [m] above the origin's ``height_m`` (0 when not
given), the same vertical reference as the cells' and samples' heights.  A cloud exported in a national grid
(UTM, Gauss-Krüger) or with sea-level heights must be shifted before the import: subtract the origin's
easting/northing and the ground height.  Two checks catch a cloud that was not:

* horizontal: the cloud's x/y box must overlap the grids' box (grid squares, not centres);
* vertical: the grids (UEs near the ground) must not lie more than :data:`MAX_BELOW_GROUND_M` below the
  cloud's ground, taken as the :data:`GROUND_PERCENTILE`-th percentile of the heights of the cloud's points
  over the grids' box (a scan holds the ground; SPEC §3).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from rflscm.data.geo import Origin
from rflscm.data.pointcloud import PointCloud
from rflscm.errors import DataError

GROUND_PERCENTILE = 2.0
"""Percentile of the heights of the cloud's points over the grids taken as its ground [%]."""
MAX_BELOW_GROUND_M = 30.0
"""Grids lower than this below the cloud's ground [m] mean the cloud's heights are in another reference."""


def _frame(origin: Origin | None) -> str:
    if origin is None:
        return "the x/y [m] frame of the samples and cells"
    return (
        f"the import's local frame (x east, y north [m] from the origin {origin.lat:.6f}, {origin.lon:.6f}; "
        f"z [m] above its height {origin.height_m:g} m)"
    )


def check_cloud_frame(
    cloud: PointCloud, name: str, grids: pd.DataFrame, grid_size_m: float, origin: Origin | None
) -> None:
    """Refuse (one line) a cloud that does not cover the grids, horizontally or in height.

    Args:
        cloud: the point cloud, in the scenario frame.
        name: its file name, for the message.
        grids: the imported grids (``x, y, z`` centres [m]).
        grid_size_m: side of a grid square [m].
        origin: the import's origin (None: x/y input).
    """
    half = grid_size_m / 2.0
    g_lo = grids[["x", "y"]].to_numpy(np.float64).min(0) - half
    g_hi = grids[["x", "y"]].to_numpy(np.float64).max(0) + half
    xy = cloud.xyz[:, :2]
    c_lo, c_hi = xy.min(0), xy.max(0)
    if (c_lo > g_hi).any() or (c_hi < g_lo).any():
        raise DataError(
            f"{name}: covers x {c_lo[0]:.0f}…{c_hi[0]:.0f} m, y {c_lo[1]:.0f}…{c_hi[1]:.0f} m, which does not "
            f"overlap the imported grids (x {g_lo[0]:.0f}…{g_hi[0]:.0f} m, y {g_lo[1]:.0f}…{g_hi[1]:.0f} m); the cloud "
            f"must be in {_frame(origin)}: shift it there (e.g. subtract the origin's easting/northing) before the import."
        )
    over = np.all((xy >= g_lo) & (xy <= g_hi), axis=1)
    heights = cloud.xyz[over, 2] if over.any() else cloud.xyz[:, 2]
    ground = float(np.percentile(heights, GROUND_PERCENTILE))
    lowest = float(grids["z"].min())
    if lowest < ground - MAX_BELOW_GROUND_M:
        raise DataError(
            f"{name}: its ground over the grids (the lowest {GROUND_PERCENTILE:g} % of its points) lies at "
            f"z = {ground:.1f} m, {ground - lowest:.1f} m above the lowest imported grid (z = {lowest:.1f} m); heights "
            f"must be in {_frame(origin)}: subtract the ground height (e.g. sea level → ground) from the cloud's z."
        )
