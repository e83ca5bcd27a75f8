"""The coordinate reference system of a scenario's map files.

A scenario's tables are in a local ENU frame [m].  With ``origin: {lat, lon}`` in scenario.yaml that frame
*is* the transverse-Mercator projection of :mod:`rflscm.data.geo` (WGS84, scale 1, centred on the origin), so
the map files carry that projection: GeoTIFFs in it, GeoJSON and KML in WGS84 lon/lat computed with
:func:`rflscm.data.geo.enu_to_geodetic` (x/y ↔ lat/lon round-trips exactly with the import path).

A scenario without an origin has no place on Earth.  Its files use the same projection around a *nominal*
origin at 0° N, 0° E (:data:`NOMINAL_ORIGIN`), so every tool still gets metres and a valid CRS, and every file
says, in its :attr:`MapFrame.note`, that the position on Earth is nominal.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rflscm.data.geo import Origin, enu_to_geodetic

NOMINAL_ORIGIN = Origin(lat=0.0, lon=0.0)
"""Origin given to a scenario without one: its maps keep their metres but sit at 0° N, 0° E."""


@dataclass(frozen=True)
class MapFrame:
    """The scenario's local frame as a CRS, and the note every file states."""

    origin: Origin
    nominal: bool
    """True when the scenario has no origin and :data:`NOMINAL_ORIGIN` stands in."""

    @staticmethod
    def of(origin: Origin | None) -> MapFrame:
        return MapFrame(NOMINAL_ORIGIN, True) if origin is None else MapFrame(origin, False)

    @property
    def proj4(self) -> str:
        """PROJ string of the local projected CRS (the projection of :mod:`rflscm.data.geo`)."""
        o = self.origin
        return (
            f"+proj=tmerc +lat_0={o.lat!r} +lon_0={o.lon!r} +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +towgs84=0,0,0 "
            "+units=m +no_defs"
        )

    @property
    def note(self) -> str:
        """One sentence on the CRS, written into every file."""
        o = self.origin
        where = (
            f"around the scenario's origin lat {o.lat:g}, lon {o.lon:g}"
            if not self.nominal
            else "around a NOMINAL origin at lat 0, lon 0: the scenario has no `origin` in scenario.yaml, so "
            "positions on Earth are not real (x/y in metres are)"
        )
        return (
            f"x/y: the scenario's local frame [m], x east, y north, transverse Mercator (WGS84, scale 1) {where}; "
            f"PROJ: {self.proj4}; lon/lat: WGS84 (EPSG:4326)"
        )

    def lonlat(self, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """WGS84 ``(lon, lat)`` [deg] of local points ``[n, 2]`` [m]."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        lat, lon, _ = enu_to_geodetic(np.column_stack([xy, np.zeros(len(xy))]), self.origin)
        return lon, lat
