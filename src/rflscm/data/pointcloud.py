"""Building / ground point clouds: PLY, LAS/LAZ and NPY, read and written.

* PLY (plyfile): a ``vertex`` element with ``x``, ``y``, ``z`` and an optional
  ``classification`` (uint8).  Written binary little-endian with float64
  coordinates, so the round trip is exact.
* LAS/LAZ (laspy, LAZ through lazrs): coordinates are scaled integers; written
  with scale 0.001 m (LAS 1.4, point format 6, full 8-bit ASPRS classes), so a
  round trip is exact to 1 mm.
* NPY: an array ``[P, 3]`` (x, y, z) or ``[P, 4]`` (+ class as 4th column);
  written ``[P, 4]`` float64 (exact).

Classes follow ASPRS LAS: 0 = never classified (also when unknown),
1 = unclassified, 2 = ground, 6 = building, …
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rflscm.data.plausibility import (
    COORDINATE_FIX,
    HEIGHT_FIX,
    HEIGHT_RANGE_M,
    MAX_HORIZONTAL_M,
    height_problem,
    horizontal_problem,
)
from rflscm.errors import DataError

POINT_CLOUD_SUFFIXES = (".ply", ".las", ".laz", ".npy")
LAS_SCALE_M = 0.001
ASPRS_CLASSES = {
    0: "never classified",
    1: "unclassified",
    2: "ground",
    3: "low vegetation",
    4: "medium vegetation",
    5: "high vegetation",
    6: "building",
    7: "low point",
    9: "water",
    17: "bridge deck",
}


@dataclass(eq=False)
class PointCloud:
    """Points of a scene scan in the scenario's ENU frame.

    Attributes:
        xyz: float64 ``[num_points, 3]`` positions [m].
        classification: uint8 ``[num_points]`` ASPRS classes (0 when unknown).
    """

    xyz: np.ndarray
    classification: np.ndarray

    def __post_init__(self) -> None:
        self.xyz = np.ascontiguousarray(self.xyz, dtype=np.float64)
        if self.xyz.ndim != 2 or self.xyz.shape[1] != 3:
            raise DataError(f"a point cloud's xyz must have shape [num_points, 3] (got {self.xyz.shape}).")
        self.classification = np.ascontiguousarray(self.classification, dtype=np.uint8).reshape(-1)
        if self.classification.shape[0] != self.xyz.shape[0]:
            raise DataError(
                f"a point cloud needs one class per point ({self.classification.shape[0]} classes, "
                f"{self.xyz.shape[0]} points)."
            )

    @property
    def num_points(self) -> int:
        return int(self.xyz.shape[0])

    def class_counts(self) -> dict[int, int]:
        """Number of points per class present."""
        classes, counts = np.unique(self.classification, return_counts=True)
        return {int(c): int(n) for c, n in zip(classes, counts, strict=True)}

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, PointCloud):
            return NotImplemented
        return np.array_equal(self.xyz, other.xyz) and np.array_equal(self.classification, other.classification)


def read_point_cloud(path: str | Path) -> PointCloud:
    """Read a ``.ply``, ``.las``, ``.laz`` or ``.npy`` point cloud.

    Raises:
        DataError: missing or unreadable file, unsupported extension, no points, or
            non-finite coordinates (naming the first bad point).
    """
    path = Path(path)
    suffix = _suffix(path)
    if path.is_dir():
        raise DataError(f"{path}: is a folder, not a point cloud file.")
    if not path.is_file():
        raise DataError(f"{path}: point cloud file not found.")
    reader = {".ply": _read_ply, ".las": _read_las, ".laz": _read_las, ".npy": _read_npy}[suffix]
    try:
        xyz, classes = reader(path)
    except DataError:
        raise
    except Exception as exc:
        message = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise DataError(f"{path.name}: not a readable {suffix[1:].upper()} point cloud ({message}).") from None
    pc = PointCloud(xyz, classes)
    if pc.num_points == 0:
        raise DataError(f"{path.name} has no points; a point cloud needs the scanned buildings and ground.")
    bad = ~np.isfinite(pc.xyz).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"{path.name} point {first + 1}: coordinates {pc.xyz[first].tolist()} are not finite; "
            f"remove such points ({int(bad.sum())} in all)."
        )
    for bad, fix in ((horizontal_problem(pc.xyz), COORDINATE_FIX), (height_problem(pc.xyz), HEIGHT_FIX)):
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            lo, hi = HEIGHT_RANGE_M
            raise DataError(
                f"{path.name} point {first + 1}: coordinates {pc.xyz[first].tolist()} are implausible "
                f"(|x|, |y| at most {MAX_HORIZONTAL_M / 1e3:g} km, z in {lo:g}…{hi:g} m); {fix}. "
                f"{int(bad.sum())} point(s) in all."
            )
    return pc


def write_point_cloud(pc: PointCloud, path: str | Path) -> None:
    """Write ``pc`` as ``.ply``, ``.las``, ``.laz`` or ``.npy`` (by extension)."""
    path = Path(path)
    suffix = _suffix(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    {".ply": _write_ply, ".las": _write_las, ".laz": _write_las, ".npy": _write_npy}[suffix](pc, path)


def _suffix(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in POINT_CLOUD_SUFFIXES:
        raise DataError(
            f"{path.name}: unsupported point cloud format {suffix or '(no extension)'!r}; "
            f"use {', '.join(POINT_CLOUD_SUFFIXES)}."
        )
    return suffix


def _read_ply(path: Path) -> tuple[np.ndarray, np.ndarray]:
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    if "vertex" not in ply:
        raise DataError(f"{path.name}: no `vertex` element; a PLY point cloud stores points as vertices.")
    vertex = ply["vertex"].data
    names = vertex.dtype.names or ()
    missing = [c for c in "xyz" if c not in names]
    if missing:
        raise DataError(f"{path.name}: vertex property(ies) {', '.join(missing)} missing; need x, y, z.")
    xyz = np.stack([np.asarray(vertex[c], dtype=np.float64) for c in "xyz"], axis=-1)
    classes = _classes(vertex["classification"], path) if "classification" in names else np.zeros(len(xyz))
    return xyz.reshape(-1, 3), classes


def _write_ply(pc: PointCloud, path: Path) -> None:
    from plyfile import PlyData, PlyElement

    vertex = np.empty(pc.num_points, dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("classification", "u1")])
    vertex["x"], vertex["y"], vertex["z"] = pc.xyz.T
    vertex["classification"] = pc.classification
    PlyData([PlyElement.describe(vertex, "vertex")], byte_order="<").write(str(path))


def _read_las(path: Path) -> tuple[np.ndarray, np.ndarray]:
    import laspy

    las = laspy.read(str(path))
    xyz = np.stack([np.asarray(las.x), np.asarray(las.y), np.asarray(las.z)], axis=-1).astype(np.float64)
    return xyz.reshape(-1, 3), np.asarray(las.classification, dtype=np.uint8)


def _write_las(pc: PointCloud, path: Path) -> None:
    import laspy

    header = laspy.LasHeader(point_format=6, version="1.4")
    header.scales = np.full(3, LAS_SCALE_M)
    header.offsets = np.floor(pc.xyz.min(axis=0)) if pc.num_points else np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = pc.xyz[:, 0], pc.xyz[:, 1], pc.xyz[:, 2]
    las.classification = pc.classification
    las.write(str(path))


def _read_npy(path: Path) -> tuple[np.ndarray, np.ndarray]:
    array = np.load(path, allow_pickle=False)
    if array.ndim != 2 or array.shape[1] not in (3, 4):
        raise DataError(
            f"{path.name}: array of shape {array.shape}; a NPY point cloud is [P, 3] (x, y, z) or [P, 4] (+ class)."
        )
    xyz = np.asarray(array[:, :3], dtype=np.float64)
    classes = _classes(array[:, 3], path) if array.shape[1] == 4 else np.zeros(len(array))
    return xyz, classes


def _write_npy(pc: PointCloud, path: Path) -> None:
    np.save(path, np.concatenate((pc.xyz, pc.classification[:, None].astype(np.float64)), axis=1))


def _classes(values: np.ndarray, path: Path) -> np.ndarray:
    """Classes as uint8; values that are not integers in 0…255 are an error naming the first point."""
    values = np.asarray(values, dtype=np.float64)
    bad = ~np.isfinite(values) | (values != np.round(values)) | (values < 0) | (values > 255)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"{path.name} point {first + 1}: classification {float(values[first])!r} is not an ASPRS class 0…255."
        )
    return values.astype(np.uint8)
