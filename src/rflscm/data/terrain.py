"""Terrain: ground elevation under cells and grids, so that ``height_m`` may be given above ground.

scenario.yaml's optional ``terrain:`` names a file in the scenario folder:

- a DEM GeoTIFF (``.tif``/``.tiff``, band 1 = elevation [m], any CRS that pyproj knows; nodata honoured),
  read with rasterio and sampled by transforming each point of the scenario's ENU frame to the DEM's CRS
  (scenario.yaml needs an ``origin`` for that);
- an XYZ table (``.csv``/``.xyz``/``.txt`` whitespace or comma separated, or ``.parquet``) with columns
  ``x, y, z`` [m] in the scenario's ENU frame on a regular grid (every x × y once).

Elevations are interpolated bilinearly.  With a terrain, a table's ``lat, lon, height_m`` rows sit at
``z = terrain(x, y) + height_m − origin.height_m`` (height above ground; the DEM's elevations and
``origin.height_m`` share one vertical datum).  Without one, ``height_m`` is absolute, as before.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pyproj
from scipy.interpolate import RegularGridInterpolator

from rflscm.data.geo import Origin
from rflscm.errors import DataError

ELEVATION_RANGE_M = (-500.0, 9000.0)
"""Plausible ground elevations [m] (Dead Sea shore … Everest, with margin)."""
RASTER_SUFFIXES = (".tif", ".tiff")


@dataclass(frozen=True)
class Terrain:
    """Ground elevation on a regular grid ``z[i_v, i_u]`` over axes ``u`` (ascending), ``v`` (ascending).

    ``to_grid`` maps ENU ``(x, y)`` to the grid's ``(u, v)`` (identity for an XYZ table in the scenario frame).
    """

    name: str
    u: np.ndarray
    v: np.ndarray
    z: np.ndarray
    transformer: pyproj.Transformer | None = None
    origin: Origin | None = None

    def _grid_coords(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        if self.transformer is None or self.origin is None:
            return xy[:, 0], xy[:, 1]
        enu = pyproj.Proj(
            proj="tmerc", lat_0=self.origin.lat, lon_0=self.origin.lon, k=1.0, x_0=0.0, y_0=0.0, ellps="WGS84"
        )
        lon, lat = enu(xy[:, 0], xy[:, 1], inverse=True)
        u, v = self.transformer.transform(lon, lat)
        return np.asarray(u, np.float64), np.asarray(v, np.float64)

    def elevation(self, xy: np.ndarray) -> np.ndarray:
        """Ground elevation [m] at ENU points ``xy [n, 2]``; NaN outside the terrain or on nodata cells."""
        u, v = self._grid_coords(np.asarray(xy, np.float64))
        inside = (u >= self.u[0]) & (u <= self.u[-1]) & (v >= self.v[0]) & (v <= self.v[-1])
        out = np.full(len(u), np.nan)
        if inside.any():
            interp = RegularGridInterpolator((self.v, self.u), self.z, method="linear")
            out[inside] = interp(np.stack((v[inside], u[inside]), axis=-1))
        return out


def load_terrain(root: Path, name: str, origin: Origin | None) -> Terrain:
    """Read ``terrain:`` (relative to the scenario folder ``root``); errors are one line naming the file."""
    base = Path(root).resolve()
    path = (base / name).resolve()
    if not path.is_relative_to(base):
        raise DataError(f"scenario.yaml: `terrain` = {name!r} lies outside the scenario folder; give a path inside it.")
    if not path.is_file():
        raise DataError(f"scenario.yaml: `terrain` = {name!r}: file not found ({path}).")
    terrain = _read_raster(path, name, origin) if path.suffix.lower() in RASTER_SUFFIXES else _read_xyz(path, name)
    finite = terrain.z[np.isfinite(terrain.z)]
    if finite.size == 0:
        raise DataError(f"{name}: the terrain holds no elevation value (all nodata).")
    lo, hi = ELEVATION_RANGE_M
    if finite.min() < lo or finite.max() > hi:
        raise DataError(
            f"{name}: elevations {finite.min():g}…{finite.max():g} m are outside the plausible {lo:g}…{hi:g} m "
            "(feet, centimetres, or a nodata value not declared in the file?)."
        )
    return terrain


def _read_raster(path: Path, name: str, origin: Origin | None) -> Terrain:
    import rasterio  # optional heavy import only for GeoTIFFs

    if origin is None:
        raise DataError(
            f"scenario.yaml: `terrain` = {name!r} is a GeoTIFF, which needs an `origin` to place the scenario's "
            "frame on the map; add `origin: {lat: …, lon: …, height_m: …}`."
        )
    try:
        with rasterio.open(path) as src:
            z = src.read(1).astype(np.float64)
            nodata, transform, crs = src.nodata, src.transform, src.crs
    except rasterio.errors.RasterioError as exc:
        raise DataError(f"{name}: cannot read the GeoTIFF ({' '.join(str(exc).split())}).") from None
    if crs is None:
        raise DataError(f"{name}: the GeoTIFF has no CRS; write one (e.g. EPSG:4326 or a UTM zone).")
    if transform.b != 0 or transform.d != 0:
        raise DataError(f"{name}: a rotated GeoTIFF is not supported; warp it north-up first (gdalwarp).")
    if nodata is not None:
        z[z == nodata] = np.nan
    rows, cols = z.shape
    if rows < 2 or cols < 2:
        raise DataError(f"{name}: the DEM needs at least 2 × 2 pixels (got {rows} × {cols}).")
    u = transform.c + transform.a * (np.arange(cols) + 0.5)  # pixel centres
    v = transform.f + transform.e * (np.arange(rows) + 0.5)
    if u[1] < u[0]:
        u, z = u[::-1], z[:, ::-1]
    if v[1] < v[0]:
        v, z = v[::-1], z[::-1, :]
    try:
        transformer = pyproj.Transformer.from_crs("EPSG:4326", crs.to_wkt(), always_xy=True)
    except pyproj.exceptions.CRSError as exc:
        raise DataError(f"{name}: unknown CRS ({exc}).") from None
    return Terrain(name, u, v, np.ascontiguousarray(z), transformer, origin)


def _read_xyz(path: Path, name: str) -> Terrain:
    try:
        if path.suffix.lower() in (".parquet", ".pq"):
            df = pd.read_parquet(path)
        else:
            df = pd.read_csv(path, sep=None, engine="python")
    except (OSError, ValueError) as exc:
        raise DataError(f"{name}: cannot read the XYZ table ({' '.join(str(exc).split())}).") from None
    df.columns = [str(c).strip().lower() for c in df.columns]
    if not {"x", "y", "z"} <= set(df.columns):
        raise DataError(f"{name}: an XYZ terrain needs columns x, y, z [m] in the scenario frame.")
    xyz = df[["x", "y", "z"]].apply(pd.to_numeric, errors="coerce").to_numpy(np.float64)
    bad = ~np.isfinite(xyz).all(axis=1)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise DataError(f"{name} row {row + 1}: x, y, z must be finite numbers (got {df.iloc[row].to_dict()}).")
    u, iu = np.unique(xyz[:, 0], return_inverse=True)
    v, iv = np.unique(xyz[:, 1], return_inverse=True)
    if len(u) < 2 or len(v) < 2 or len(xyz) != len(u) * len(v) or len(set(zip(iu, iv, strict=True))) != len(xyz):
        raise DataError(
            f"{name}: an XYZ terrain must be a regular grid, every x × y once ({len(u)} × {len(v)} needs "
            f"{len(u) * len(v)} rows, got {len(xyz)})."
        )
    z = np.empty((len(v), len(u)))
    z[iv, iu] = xyz[:, 2]
    return Terrain(name, u, v, z)
