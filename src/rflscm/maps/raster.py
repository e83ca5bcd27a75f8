"""Grids (points at grid centres) → a raster lattice, and the GeoTIFF writer (rasterio)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rflscm.errors import DataError
from rflscm.maps.crs import MapFrame

MAX_PIXELS = 50_000_000
"""A lattice larger than this means grids that are not on a regular spacing; refused rather than written."""


@dataclass(frozen=True)
class Lattice:
    """Pixel of every grid on a square lattice of pixel size :attr:`size_m`, pixel centres at grid centres."""

    size_m: float
    x_min: float
    y_max: float
    width: int
    height: int
    col: np.ndarray
    row: np.ndarray

    @staticmethod
    def of(xy: np.ndarray) -> Lattice:
        """The lattice of grid centres ``[num_grids, 2]`` [m].

        The pixel size is the smallest spacing between distinct grid x or y coordinates (10 m for a 10 m
        grid; coordinates rounded to the millimetre first), so no two grids ever share a pixel.
        """
        xy = np.round(np.asarray(xy, np.float64).reshape(-1, 2), 3)
        steps = [np.diff(np.unique(xy[:, k])) for k in (0, 1)]
        positive = np.concatenate(steps)
        size = float(positive.min()) if positive.size else 10.0
        x_min, y_max = float(xy[:, 0].min()), float(xy[:, 1].max())
        col = np.round((xy[:, 0] - x_min) / size).astype(np.int64)
        row = np.round((y_max - xy[:, 1]) / size).astype(np.int64)
        width, height = int(col.max()) + 1, int(row.max()) + 1
        if width * height > MAX_PIXELS:
            raise DataError(
                f"the grids are not on a regular spacing: their smallest coordinate step, {size:g} m, would make a "
                f"{width} × {height} raster; give grids on a lattice (e.g. 10 m) to write GeoTIFFs."
            )
        return Lattice(size, x_min, y_max, width, height, col, row)

    def image(self, values: np.ndarray, nodata: float) -> np.ndarray:
        """``[height, width]`` image of per-grid ``values`` with ``nodata`` elsewhere (and where values are NaN)."""
        values = np.asarray(values)
        out = np.full((self.height, self.width), nodata, dtype=values.dtype)
        out[self.row, self.col] = values
        if values.dtype.kind == "f" and not np.isnan(nodata):
            out[np.isnan(out)] = nodata
        return out


@dataclass(frozen=True)
class Band:
    """One band of a GeoTIFF: per-grid values and their description."""

    values: np.ndarray
    description: str


def write_geotiff(
    path: Path, lattice: Lattice, frame: MapFrame, bands: list[Band], dtype: str, nodata: float, unit: str, title: str
) -> Path:
    """One GeoTIFF (one band per carrier) in the scenario's local projected CRS, with its note as a tag."""
    import rasterio
    from rasterio.crs import CRS
    from rasterio.transform import Affine

    half = lattice.size_m / 2.0
    transform = Affine(lattice.size_m, 0.0, lattice.x_min - half, 0.0, -lattice.size_m, lattice.y_max + half)
    profile = {
        "driver": "GTiff",
        "width": lattice.width,
        "height": lattice.height,
        "count": len(bands),
        "dtype": dtype,
        "crs": CRS.from_proj4(frame.proj4),
        "transform": transform,
        "nodata": nodata,
        "compress": "deflate",
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    with rasterio.open(path, "w", **profile) as dst:
        for i, band in enumerate(bands, start=1):
            dst.write(lattice.image(np.asarray(band.values).astype(dtype), nodata), i)
            dst.set_band_description(i, band.description)
            dst.set_band_unit(i, unit)
        dst.update_tags(TITLE=title, UNIT=unit, CRS_NOTE=frame.note, PIXEL_SIZE_M=f"{lattice.size_m:g}")
    return path
