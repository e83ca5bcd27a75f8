"""Plausibility of a scenario's geometry: limits that no real radio scene breaks (issue 14).

A table can be well formed and still be nonsense for a city-scale channel model: UTM coordinates next to
local metres, a height in millimetres, one coordinate of 1e308.  Such scenes pass the per-column checks
but make a model try to voxelise a box of thousands of kilometres.  ``rflscm check`` therefore refuses:

* a position more than :data:`MAX_HORIZONTAL_M` from the frame's origin in x or y (per row);
* a height ``z`` outside :data:`HEIGHT_RANGE_M` (per row);
* cells, grids and point cloud whose bounding boxes lie more than :data:`MAX_GAP_M` apart horizontally
  or :data:`MAX_VERTICAL_GAP_M` apart vertically (the message says by how much they miss).

The limits and their reasons are listed in README "Validation" and docs/DECISIONS.md.
"""

from __future__ import annotations

import numpy as np

from rflscm.errors import DataError

MAX_HORIZONTAL_M = 200e3
"""|x| and |y| of any position [m]: the local frame is centred on the scene (same limit as lat/lon input)."""
HEIGHT_RANGE_M = (-500.0, 9000.0)
"""z of any position [m]: below the Dead Sea shore to above Everest, in metres relative to the frame."""
MAX_GAP_M = 5e3
"""Largest horizontal distance [m] between the boxes of the cells, the grids and the point cloud."""
MAX_VERTICAL_GAP_M = 2e3
"""Largest vertical distance [m] between those boxes."""

COORDINATE_FIX = (
    "x/y/z are metres in a local frame centred on the scene (UTM or other projected coordinates? subtract a "
    "centre point, or give lat/lon/height_m with an `origin` in scenario.yaml)"
)
HEIGHT_FIX = "heights are metres (millimetres, feet or an absolute height against a local frame?)"


def horizontal_problem(xyz: np.ndarray) -> np.ndarray:
    """bool ``[num_points]``: x or y not finite or farther than :data:`MAX_HORIZONTAL_M` from the origin."""
    xy = xyz[:, :2]
    return ~np.isfinite(xy).all(axis=1) | (np.abs(xy) > MAX_HORIZONTAL_M).any(axis=1)


def height_problem(xyz: np.ndarray) -> np.ndarray:
    """bool ``[num_points]``: z outside :data:`HEIGHT_RANGE_M`."""
    lo, hi = HEIGHT_RANGE_M
    z = xyz[:, 2]
    return ~np.isfinite(z) | (z < lo) | (z > hi)


def _box(xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return xyz.min(axis=0), xyz.max(axis=0)


def _gap(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Per-axis distance ``[3]`` [m] between two boxes (0 where they overlap on that axis)."""
    return np.maximum(0.0, np.maximum(b[0] - a[1], a[0] - b[1]))


def _describe(name: str, box: tuple[np.ndarray, np.ndarray]) -> str:
    lo, hi = box
    return f"{name} x {lo[0]:.6g}…{hi[0]:.6g}, y {lo[1]:.6g}…{hi[1]:.6g}, z {lo[2]:.6g}…{hi[2]:.6g} m"


def check_overlap(parts: list[tuple[str, np.ndarray]]) -> None:
    """Every pair of ``(name, xyz [n, 3])`` lies within :data:`MAX_GAP_M` (horizontal) and
    :data:`MAX_VERTICAL_GAP_M` (vertical) of each other; otherwise a :class:`DataError` saying by how much."""
    boxes = [(name, _box(xyz)) for name, xyz in parts if len(xyz)]
    for i, (name_a, box_a) in enumerate(boxes):
        for name_b, box_b in boxes[i + 1 :]:
            gap = _gap(box_a, box_b)
            horizontal, vertical = float(np.hypot(gap[0], gap[1])), float(gap[2])
            if horizontal <= MAX_GAP_M and vertical <= MAX_VERTICAL_GAP_M:
                continue
            miss = (
                f"{horizontal / 1e3:.3g} km apart horizontally (at most {MAX_GAP_M / 1e3:g} km)"
                if horizontal > MAX_GAP_M
                else f"{vertical:.4g} m apart vertically (at most {MAX_VERTICAL_GAP_M:g} m)"
            )
            raise DataError(
                f"{name_a} and {name_b} do not cover the same place: they are {miss} "
                f"({_describe(name_a, box_a)}; {_describe(name_b, box_b)}); are both in the same coordinate frame "
                "and unit?"
            )


MAX_GROUND_UE_HEIGHT_M = 500.0
"""Largest height [m] of a grid above the lowest point of the scene (cells, grids, point cloud) for ground UEs;
a scenario declaring ``ue: aerial`` in scenario.yaml may go up to :data:`HEIGHT_RANGE_M`."""
UE_KINDS = ("ground", "aerial")


def check_grid_heights(grids_xyz: np.ndarray, others: list[np.ndarray], ue: str, grids_name: str) -> None:
    """Grids of ground UEs lie at most :data:`MAX_GROUND_UE_HEIGHT_M` above the lowest point of the scene
    (``grids_xyz`` and every array in ``others``); a :class:`DataError` names the first grid that does not."""
    if ue == "aerial" or not len(grids_xyz):
        return
    lows = [float(np.nanmin(a[:, 2])) for a in (grids_xyz, *others) if len(a)]
    ground = min(lows)
    z = grids_xyz[:, 2]
    above = np.flatnonzero(z - ground > MAX_GROUND_UE_HEIGHT_M)
    if above.size:
        first = int(above[0])
        raise DataError(
            f"{grids_name} row {first + 1}: z = {z[first]:.6g} m is {z[first] - ground:.6g} m above the lowest point "
            f"of the scene ({ground:.6g} m), more than the {MAX_GROUND_UE_HEIGHT_M:g} m a ground UE can be "
            f"({above.size} grid(s)); {HEIGHT_FIX} For drones or aircraft add `ue: aerial` to scenario.yaml."
        )
