"""GeoJSON (RFC 7946: WGS84 lon/lat, x/y in the properties) and KML of grids, cells and measured points."""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from rflscm.maps.crs import MapFrame
from rflscm.maps.style import CELL, CHANGED_CELL, RSRP

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario

WEDGE_HALF_ANGLE_DEG = 30.0
"""Half opening of a drawn sector wedge [deg] (a drawing convention, not the antenna's beamwidth)."""
Props = dict[str, object]


def _clean(value: object) -> object:
    """JSON-safe scalars: numpy → Python, NaN → None."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def square(x: float, y: float, size: float) -> np.ndarray:
    """Closed ring ``[5, 2]`` of the grid square centred at ``(x, y)`` [m]."""
    h = size / 2.0
    return np.array([[x - h, y - h], [x + h, y - h], [x + h, y + h], [x - h, y + h], [x - h, y - h]])


def wedge(x: float, y: float, azimuth_deg: float, radius_m: float, steps: int = 8) -> np.ndarray:
    """Closed ring of a sector wedge at the site ``(x, y)`` pointing at ``azimuth_deg`` (clockwise from north)."""
    a = np.deg2rad(azimuth_deg + np.linspace(-WEDGE_HALF_ANGLE_DEG, WEDGE_HALF_ANGLE_DEG, steps))
    arc = np.column_stack([x + radius_m * np.sin(a), y + radius_m * np.cos(a)])
    return np.vstack([[x, y], arc, [x, y]])


def _ring_lonlat(frame: MapFrame, ring: np.ndarray) -> list[list[float]]:
    lon, lat = frame.lonlat(ring)
    return [[float(a), float(b)] for a, b in zip(lon, lat, strict=True)]


def feature_collection(frame: MapFrame, features: list[dict], name: str) -> dict:
    return {
        "type": "FeatureCollection",
        "name": name,
        "crs_note": frame.note,
        "x_y_proj4": frame.proj4,
        "nominal_origin": frame.nominal,
        "features": features,
    }


def polygon_feature(frame: MapFrame, ring_xy: np.ndarray, props: Props) -> dict:
    return {
        "type": "Feature",
        "geometry": {"type": "Polygon", "coordinates": [_ring_lonlat(frame, ring_xy)]},
        "properties": {k: _clean(v) for k, v in props.items()},
    }


def point_feature(frame: MapFrame, x: float, y: float, props: Props) -> dict:
    lon, lat = frame.lonlat(np.array([[x, y]]))
    return {
        "type": "Feature",
        "geometry": {"type": "Point", "coordinates": [float(lon[0]), float(lat[0])]},
        "properties": {k: _clean(v) for k, v in props.items()},
    }


def write_geojson(path: Path, collection: dict) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(collection, allow_nan=False, separators=(",", ":")))
    return path


def cell_rows(scenario: Scenario, before: int, after: int | None) -> list[Props]:
    """One property row per cell and shown round: settings, position, and the change from ``before`` to
    ``after`` (azimuth, tilts, codebooks) when ``after`` is given."""
    rows: list[Props] = []
    rounds = [before] if after is None else [before, after]
    b = scenario.cells[before].set_index("cell_id")
    a = None if after is None else scenario.cells[after].set_index("cell_id")
    for rnd in rounds:
        table = scenario.cells[rnd]
        for _, c in table.iterrows():
            cid = int(c["cell_id"])
            row: Props = {
                "cell_id": cid,
                "site_id": int(c["site_id"]),
                "round": rnd,
                "x": float(c["x"]),
                "y": float(c["y"]),
                "z": float(c["z"]),
                "azimuth_deg": float(c["azimuth_deg"]),
                "mech_tilt_deg": float(c["mech_tilt_deg"]),
                "elec_tilt_deg": float(c["elec_tilt_deg"]),
                "freq_ghz": float(c["freq_hz"]) / 1e9,
                "tx_power_dbm": float(c["tx_power_dbm"]),
                "ssb_codebook": str(c["ssb_codebook"]),
                "csi_codebook": str(c["csi_codebook"]),
            }
            if a is not None:
                d_az = (float(a.loc[cid, "azimuth_deg"]) - float(b.loc[cid, "azimuth_deg"]) + 180.0) % 360.0 - 180.0
                d_mech = float(a.loc[cid, "mech_tilt_deg"]) - float(b.loc[cid, "mech_tilt_deg"])
                d_elec = float(a.loc[cid, "elec_tilt_deg"]) - float(b.loc[cid, "elec_tilt_deg"])
                codebooks = (
                    a.loc[cid, ["ssb_codebook", "csi_codebook"]] != b.loc[cid, ["ssb_codebook", "csi_codebook"]]
                ).any()
                row |= {
                    "change": f"round {before} → round {after}",
                    "d_azimuth_deg": d_az,
                    "d_mech_tilt_deg": d_mech,
                    "d_elec_tilt_deg": d_elec,
                    "codebook_changed": bool(codebooks),
                    "changed": bool(abs(d_az) > 1e-9 or abs(d_mech) > 1e-9 or abs(d_elec) > 1e-9 or codebooks),
                }
            else:
                row["changed"] = False
            rows.append(row)
    return rows


def wedge_radius(scenario: Scenario, row: Props) -> float:
    """Drawn wedge radius [m]: 6 % of the scene's extent, shorter for higher carriers so co-sited ones show."""
    xy = np.vstack([scenario.grids[["x", "y"]].to_numpy(), scenario.cells[1][["x", "y"]].to_numpy()])
    span = float(np.ptp(xy, axis=0).max()) if len(xy) > 1 else 100.0
    freqs = sorted({float(f) for f in scenario.cells[1]["freq_hz"]})
    rank = freqs.index(float(row["freq_ghz"]) * 1e9) if float(row["freq_ghz"]) * 1e9 in freqs else 0  # type: ignore[arg-type]
    return max(15.0, 0.06 * span) * (1.0 - 0.25 * rank / max(1, len(freqs) - 1))


def measured_rows(scenario: Scenario, round: int) -> list[Props]:
    """Per grid measured in ``round``: its position, the cells and SSB reports there, the best measured SSB."""
    m = scenario.measurements
    m = m[((m["round"] == round) & (m["beam_type"] == "ssb")).to_numpy()]
    if m.empty:
        return []
    reported = m[np.isfinite(m["rsrp_dbm"].to_numpy())]
    grids = scenario.grids.set_index("grid_id")
    rows: list[Props] = []
    best = reported.sort_values("rsrp_dbm", ascending=False).drop_duplicates("grid_id").set_index("grid_id")
    for gid, group in m.groupby("grid_id", sort=True):
        g = int(gid)
        rows.append(
            {
                "grid_id": g,
                "round": round,
                "x": float(grids.loc[g, "x"]),
                "y": float(grids.loc[g, "y"]),
                "cells_measured": int(group["cell_id"].nunique()),
                "ssb_reports": int(np.isfinite(group["rsrp_dbm"].to_numpy()).sum()),
                "best_measured_ssb_rsrp_dbm": float(best.loc[g, "rsrp_dbm"]) if g in best.index else None,
                "best_measured_cell_id": int(best.loc[g, "cell_id"]) if g in best.index else None,
            }
        )
    return rows


# ---- KML ----------------------------------------------------------------------------------------------
def _kml_colour(hex_colour: str, alpha: int = 0xB0) -> str:
    """KML's aabbggrr from ``#rrggbb``."""
    r, g, b = hex_colour[1:3], hex_colour[3:5], hex_colour[5:7]
    return f"{alpha:02x}{b}{g}{r}"


def _coords(frame: MapFrame, ring: np.ndarray) -> str:
    return " ".join(f"{lon:.8f},{lat:.8f},0" for lon, lat in _ring_lonlat(frame, ring))


def _data(parent: ET.Element, props: Props) -> None:
    ext = ET.SubElement(parent, "ExtendedData")
    for k, v in props.items():
        d = ET.SubElement(ext, "Data", name=k)
        ET.SubElement(d, "value").text = "" if _clean(v) is None else str(_clean(v))


def write_kml(
    path: Path,
    frame: MapFrame,
    title: str,
    grid_folders: list[tuple[str, list[Props], np.ndarray, str]],
    size_m: float,
    cells: list[Props],
    radius: list[float],
    measured: list[Props],
) -> Path:
    """KML for Google Earth: one folder per (round, carrier) of grid squares coloured by ``rsrp_key`` (every KPI
    in ExtendedData), the cells as wedges (changed ones red) and the measured points."""
    kml = ET.Element("kml", xmlns="http://www.opengis.net/kml/2.2")
    doc = ET.SubElement(kml, "Document")
    ET.SubElement(doc, "name").text = title
    ET.SubElement(doc, "description").text = frame.note
    for name, rows, rsrp, _ in grid_folders:
        folder = ET.SubElement(doc, "Folder")
        ET.SubElement(folder, "name").text = name
        ET.SubElement(folder, "visibility").text = "1" if name == grid_folders[0][0] else "0"
        for row, colour in zip(rows, RSRP.colours(rsrp), strict=True):
            pm = ET.SubElement(folder, "Placemark")
            ET.SubElement(pm, "name").text = f"grid {row['grid_id']}"
            style = ET.SubElement(ET.SubElement(pm, "Style"), "PolyStyle")
            ET.SubElement(style, "color").text = _kml_colour(colour or "#888888", 0xB0 if colour else 0x30)
            ET.SubElement(style, "outline").text = "0"
            _data(pm, row)
            ring = square(float(row["x"]), float(row["y"]), size_m)  # type: ignore[arg-type]
            poly = ET.SubElement(ET.SubElement(ET.SubElement(pm, "Polygon"), "outerBoundaryIs"), "LinearRing")
            ET.SubElement(poly, "coordinates").text = _coords(frame, ring)
    folder = ET.SubElement(doc, "Folder")
    ET.SubElement(folder, "name").text = "cells (azimuth clockwise from north; red: changed)"
    for row, r in zip(cells, radius, strict=True):
        pm = ET.SubElement(folder, "Placemark")
        ET.SubElement(pm, "name").text = f"cell {row['cell_id']} (round {row['round']})"
        st = ET.SubElement(pm, "Style")
        ET.SubElement(ET.SubElement(st, "PolyStyle"), "color").text = _kml_colour(
            CHANGED_CELL if row.get("changed") else CELL, 0x90
        )
        _data(pm, row)
        ring = wedge(float(row["x"]), float(row["y"]), float(row["azimuth_deg"]), r)  # type: ignore[arg-type]
        poly = ET.SubElement(ET.SubElement(ET.SubElement(pm, "Polygon"), "outerBoundaryIs"), "LinearRing")
        ET.SubElement(poly, "coordinates").text = _coords(frame, ring)
    folder = ET.SubElement(doc, "Folder")
    ET.SubElement(folder, "name").text = "measured points"
    ET.SubElement(folder, "visibility").text = "0"
    for row in measured:
        pm = ET.SubElement(folder, "Placemark")
        ET.SubElement(pm, "name").text = f"measured grid {row['grid_id']}"
        _data(pm, row)
        lon, lat = frame.lonlat(np.array([[row["x"], row["y"]]], dtype=np.float64))
        ET.SubElement(ET.SubElement(pm, "Point"), "coordinates").text = f"{lon[0]:.8f},{lat[0]:.8f},0"
    path.parent.mkdir(parents=True, exist_ok=True)
    ET.ElementTree(kml).write(path, encoding="utf-8", xml_declaration=True)
    return path


def grid_table(scenario: Scenario, frame: MapFrame) -> pd.DataFrame:
    """``grid_id``, ``x``, ``y``, ``z`` [m], ``lat``, ``lon`` [deg] of every grid (the scenario's order)."""
    g = scenario.grids[["grid_id", "x", "y", "z"]].reset_index(drop=True).copy()
    lon, lat = frame.lonlat(g[["x", "y"]].to_numpy())
    g["lat"], g["lon"] = lat, lon
    return g


def with_grid_positions(table: pd.DataFrame, scenario: Scenario) -> pd.DataFrame:
    """``table`` with each row's grid position beside its ``grid_id``: ``x``, ``y`` [m] in the scenario's frame
    and, when scenario.yaml has an ``origin``, ``lat``, ``lon`` [deg, WGS84] (:mod:`rflscm.maps.crs`)."""
    frame = MapFrame.of(scenario.meta.origin)
    grids = grid_table(scenario, frame)
    keep = ["grid_id", "x", "y"] + ([] if frame.nominal else ["lat", "lon"])
    pos = grids[keep].set_index("grid_id").loc[table["grid_id"].to_numpy()].reset_index(drop=True)
    at = list(table.columns).index("grid_id") + 1
    out = table.reset_index(drop=True)
    return pd.concat([out.iloc[:, :at], pos, out.iloc[:, at:]], axis=1)
