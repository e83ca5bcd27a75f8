"""The interactive map: one self-contained HTML file (folium's Leaflet map with Leaflet itself inlined from
``vendor/``; no network at run time).

Layers are built in the page from one compact data object (grid squares, per-layer colours, per-grid popup
rows), so the file stays small: one overlay per (round, carrier, KPI), the differences, the cells (changed ones
red) and the measured grids, a layer control listing them all, and a legend with units.  A click on a grid
opens its popup: every cell's predicted best-beam SSB RSRP and SS-SINR there (the strongest
:data:`POPUP_CELLS`) and a small PNG of the serving cell's APS.
"""

from __future__ import annotations

import base64
import html
import io
import json
import re
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from rflscm.errors import DataError
from rflscm.geometry.angles import internal_to_engineering
from rflscm.maps.style import COVERED, DIFF, NOT_COVERED, RSRP, SINR, Scale, serving_colours
from rflscm.maps.vector import Props, square, wedge

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.eval.cache import APSCache
    from rflscm.maps.write import MapOutputs

POPUP_CELLS = 12
"""Cells listed in a grid's popup, strongest first, per carrier."""
APS_RANGE_DB = 30.0
"""Dynamic range of the popup's APS image [dB] below its strongest bin."""


def _vendor(name: str) -> str:
    return resources.files("rflscm.maps").joinpath("vendor", name).read_text(encoding="utf-8")


def aps_png(aps: np.ndarray, el_rad: np.ndarray, az_rad: np.ndarray) -> str:
    """A tiny PNG data URI of one APS ``[num_bins]``: azimuth clockwise from north (0…360°) across, elevation up
    the image, power in dB over :data:`APS_RANGE_DB` below the peak (viridis, 16 levels)."""
    from matplotlib import colormaps
    from PIL import Image

    az_deg, _ = internal_to_engineering(el_rad, az_rad)
    els, row = np.unique(np.round(el_rad, 9), return_inverse=True)
    azs, col = np.unique(np.round(az_deg, 6), return_inverse=True)
    db = np.full((len(els), len(azs)), -np.inf)
    with np.errstate(divide="ignore"):
        db[row, col] = 10.0 * np.log10(np.maximum(aps, 0.0))
    peak = db.max() if np.isfinite(db).any() else 0.0
    level = np.clip(np.round((db - peak + APS_RANGE_DB) / APS_RANGE_DB * 15.0), 0, 15).astype(np.uint8)[::-1]
    img = Image.fromarray(level, mode="P")
    palette = (np.array([colormaps["viridis"](i / 15.0)[:3] for i in range(16)]) * 255).astype(np.uint8)
    img.putpalette(palette.ravel().tolist())
    img = img.resize((len(azs) * 2, len(els) * 2), Image.Resampling.NEAREST)
    buf = io.BytesIO()
    img.save(buf, format="PNG", optimize=True)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode()


def _round1(values: np.ndarray) -> list[float | None]:
    return [None if not np.isfinite(v) else round(float(v), 1) for v in np.asarray(values, np.float64)]


def _scale_legend(scale: Scale, label: str) -> dict:
    return {"label": label, "colours": scale.gradient(), "low": scale.low, "high": scale.high, "unit": scale.unit}


def page_data(
    cache: APSCache,
    scenario: Scenario,
    outputs: MapOutputs,
    grids: pd.DataFrame,
    cells: list[Props],
    radius: list[float],
    measured: list[Props],
    title: str,
) -> dict:
    """The page's data object: grid squares [lat, lon], layers (name, kind, colours), popups, cells, legend."""
    frame, size, layers = outputs.frame, outputs.lattice.size_m, outputs.layers
    xy = grids[["x", "y"]].to_numpy()
    squares = []
    for x, y in xy:
        lon, lat = frame.lonlat(square(x, y, size)[:4])
        squares.append([[round(float(a), 7), round(float(b), 7)] for a, b in zip(lat, lon, strict=True)])
    overlays: list[dict] = []
    popups: dict[str, list] = {}
    aps_pairs: set[tuple[int, int]] = set()
    gids = grids["grid_id"].to_numpy()
    for lay in layers:
        for c in lay.carriers:
            head = f"round {lay.round} · {c.label}"
            overlays += [
                {"name": f"{head} · best-server RSRP (dBm)", "colours": RSRP.colours(c.rsrp_dbm)},
                {"name": f"{head} · serving cell", "colours": serving_colours(c.serving, scenario.cell_ids())},
                {"name": f"{head} · SS-SINR (dB)", "colours": SINR.colours(c.sinr_db)},
                {
                    "name": f"{head} · coverage (RSRP ≥ {lay.threshold_dbm:g} dBm)",
                    "colours": [None if np.isnan(v) else (COVERED if v else NOT_COVERED) for v in c.covered],
                },
            ]
            for ov in overlays[-4:]:
                ov["popup"] = f"{lay.round}|{c.key}"
            rows = []
            for g in range(len(gids)):
                finite = np.flatnonzero(np.isfinite(c.cell_rsrp_dbm[:, g]))
                order = finite[np.argsort(-c.cell_rsrp_dbm[finite, g])][:POPUP_CELLS]
                rows.append(
                    [
                        [
                            int(c.cell_ids[i]),
                            round(float(c.cell_rsrp_dbm[i, g]), 1),
                            round(float(c.cell_sinr_db[i, g]), 1),
                        ]
                        for i in order
                    ]
                )
                if c.serving[g] >= 0:
                    aps_pairs.add((int(c.serving[g]), int(gids[g])))
            popups[f"{lay.round}|{c.key}"] = [
                rows,
                [int(s) for s in c.serving],
                _round1(c.rsrp_dbm),
                _round1(c.sinr_db),
                head,
            ]
    if len(layers) == 2:
        a, b = layers
        for x, y in zip(a.carriers, b.carriers, strict=True):
            head = f"round {b.round} − round {a.round} · {x.label}"
            moved = np.where((x.serving >= 0) & (y.serving >= 0), (x.serving != y.serving).astype(float), np.nan)
            overlays += [
                {
                    "name": f"{head} · RSRP change (dB)",
                    "colours": DIFF.colours(y.rsrp_dbm - x.rsrp_dbm),
                    "popup": f"{b.round}|{x.key}",
                },
                {
                    "name": f"{head} · SS-SINR change (dB)",
                    "colours": DIFF.colours(y.sinr_db - x.sinr_db),
                    "popup": f"{b.round}|{x.key}",
                },
                {
                    "name": f"{head} · serving cell changed (red)",
                    "colours": [None if np.isnan(v) else ("#e31a1c" if v else "#d9d9d9") for v in moved],
                    "popup": f"{b.round}|{x.key}",
                },
            ]
    aps = {}
    if aps_pairs:
        pairs = sorted(aps_pairs)
        cell_ids = np.array([p[0] for p in pairs])
        grid_ids = np.array([p[1] for p in pairs])
        xyz = scenario.grids.set_index("grid_id").loc[grid_ids, ["x", "y", "z"]].to_numpy()
        x = cache.aps(cell_ids, grid_ids, xyz).detach().cpu().double().numpy()
        el, az = cache.angle_grid.bin_angles()
        aps = {f"{c}:{g}": aps_png(x[i], el, az) for i, (c, g) in enumerate(pairs)}
    cell_items = []
    for row, r in zip(cells, radius, strict=True):
        lon, lat = frame.lonlat(wedge(float(row["x"]), float(row["y"]), float(row["azimuth_deg"]), r))  # type: ignore[arg-type]
        cell_items.append(
            {
                "ring": [[round(float(b), 7), round(float(a), 7)] for a, b in zip(lon, lat, strict=True)],
                "round": row["round"],
                "changed": bool(row.get("changed")),
                "text": ", ".join(f"{k} {v}" for k, v in row.items() if k not in ("x", "y", "z")),
            }
        )
    points = []
    for p in measured:
        lon, lat = frame.lonlat(np.array([[p["x"], p["y"]]], dtype=np.float64))
        points.append(
            {
                "at": [float(lat[0]), float(lon[0])],
                "round": p["round"],
                "text": ", ".join(f"{k} {v}" for k, v in p.items() if k not in ("x", "y")),
            }
        )
    rounds = [lay.round for lay in layers]
    return {
        "title": html.escape(title),
        "note": html.escape(frame.note),
        "grids": {"ids": [int(g) for g in gids], "xy": [[float(a), float(b)] for a, b in xy], "squares": squares},
        "overlays": overlays,
        "popups": popups,
        "aps": aps,
        "cells": cell_items,
        "cell_rounds": sorted({int(c["round"]) for c in cells}),  # type: ignore[call-overload]
        "points": points,
        "rounds": rounds,
        "pairs": layers[0].pairs,
        "legend": [
            _scale_legend(RSRP, "best-server SSB RSRP"),
            _scale_legend(SINR, "SS-SINR"),
            *([_scale_legend(DIFF, "round difference")] if len(layers) == 2 else []),
        ],
        "threshold_dbm": layers[0].threshold_dbm,
    }


_SCRIPT = """
(function () {
  const map = %(map)s;
  const D = %(data)s;
  window.rflscmData = D;
  window.rflscmMap = map;
  const overlays = {};
  function popupHtml(g, key) {
    const P = D.popups[key];
    if (!P) return "no prediction";
    const [rows, serving, rsrp, sinr, head] = P;
    let h = `<div class="rflscm-popup"><b>grid ${D.grids.ids[g]}</b> (x ${D.grids.xy[g][0]} m, y ${D.grids.xy[g][1]} m)<br>${head}<br>`;
    h += `best-server RSRP ${rsrp[g] === null ? "–" : rsrp[g] + " dBm"}, SS-SINR ${sinr[g] === null ? "–" : sinr[g] + " dB"}`;
    h += `<table><tr><th>cell</th><th>RSRP (dBm)</th><th>SINR (dB)</th></tr>`;
    for (const [c, r, s] of rows[g]) {
      const b = c === serving[g];
      h += `<tr${b ? ' style="font-weight:bold"' : ""}><td>${c}${b ? " (serving)" : ""}</td><td>${r}</td><td>${s}</td></tr>`;
    }
    h += "</table>";
    const img = D.aps[`${serving[g]}:${D.grids.ids[g]}`];
    if (img) h += `<div>APS of serving cell ${serving[g]} (azimuth 0–360° clockwise from north across, elevation up; ${%(range)s} dB range)</div><img class="rflscm-aps" src="${img}">`;
    return h + "</div>";
  }
  D.overlays.forEach(function (ov, k) {
    const group = L.featureGroup();
    ov.colours.forEach(function (colour, g) {
      if (colour === null) return;
      const poly = L.polygon(D.grids.squares[g], {stroke: false, fillColor: colour, fillOpacity: 0.8,
                                                className: "rflscm-grid"});
      poly.bindPopup(function () { return popupHtml(g, ov.popup); }, {maxWidth: 420});
      group.addLayer(poly);
    });
    overlays[ov.name] = group;
    if (k === 0) group.addTo(map);
  });
  D.cell_rounds.forEach(function (r, k) {
    const group = L.featureGroup();
    D.cells.filter(c => c.round === r).forEach(function (c) {
      L.polygon(c.ring, {color: c.changed ? "%(changed)s" : "%(cell)s", weight: c.changed ? 3 : 1,
                         fillOpacity: c.changed ? 0.55 : 0.35, className: "rflscm-cell"})
        .bindTooltip(c.text).addTo(group);
    });
    overlays[`cells · round ${r} (red: changed)`] = group;
    if (k === D.cell_rounds.length - 1) group.addTo(map);
  });
  const measured = L.featureGroup();
  D.points.forEach(p => L.circleMarker(p.at, {radius: 2, color: "#000", weight: 1}).bindTooltip(p.text).addTo(measured));
  overlays["measured grids"] = measured;
  L.control.layers(null, overlays, {collapsed: false}).addTo(map);
  const legend = L.control({position: "bottomleft"});
  legend.onAdd = function () {
    const div = L.DomUtil.create("div", "rflscm-legend");
    let h = `<b>${D.title}</b><br>`;
    for (const s of D.legend) {
      h += `<div>${s.label} (${s.unit})</div><div class="bar" style="background:linear-gradient(to right,${s.colours.join(",")})"></div>`;
      h += `<div class="ends"><span>≤ ${s.low}</span><span>≥ ${s.high}</span></div>`;
    }
    h += `<div><span class="sw" style="background:%(covered)s"></span>covered (RSRP ≥ ${D.threshold_dbm} dBm) <span class="sw" style="background:%(uncovered)s"></span>not covered</div>`;
    h += `<div>serving cell: one colour per cell id (click a grid for the id)</div>`;
    h += `<div><span class="sw" style="background:%(cell)s"></span>cell <span class="sw" style="background:%(changed)s"></span>changed cell; wedges point along the azimuth</div>`;
    h += `<div class="note">predicted on ${D.pairs}. ${D.note}</div>`;
    div.innerHTML = h;
    return div;
  };
  legend.addTo(map);
  const all = D.grids.squares.flat();
  if (all.length) map.fitBounds(L.latLngBounds(all));
})();
"""

_CSS = """
.rflscm-legend {background: rgba(255,255,255,0.92); padding: 6px 8px; font: 12px sans-serif; max-width: 330px;}
.rflscm-legend .bar {height: 10px; width: 220px;}
.rflscm-legend .ends {display: flex; justify-content: space-between; width: 220px; font-size: 11px;}
.rflscm-legend .sw {display: inline-block; width: 10px; height: 10px; margin: 0 3px;}
.rflscm-legend .note {font-size: 10px; color: #444; margin-top: 4px;}
.rflscm-popup table {border-collapse: collapse; font-size: 11px;} .rflscm-popup td {padding: 0 6px; text-align: right;}
.rflscm-aps {image-rendering: pixelated; border: 1px solid #999;}
"""


def write_html(
    path: Path,
    cache: APSCache,
    scenario: Scenario,
    outputs: MapOutputs,
    grids: pd.DataFrame,
    cells: list[Props],
    radius: list[float],
    measured: list[Props],
    title: str,
) -> Path:
    """Write the self-contained interactive map (see the module docstring)."""
    import folium
    from branca.element import Element, Figure, MacroElement
    from jinja2 import Template

    data = page_data(cache, scenario, outputs, grids, cells, radius, measured, title)
    o = outputs.frame.origin
    fmap = folium.Map(location=[o.lat, o.lon], zoom_start=16, tiles=None, control_scale=True)
    fmap.default_js, fmap.default_css = [], []  # folium links CDNs; Leaflet is inlined below instead
    root = fmap.get_root()
    assert isinstance(root, Figure)
    root.header.add_child(
        Element(f"<style>{_vendor('leaflet.css')}</style>\n<style>{_CSS}</style>"), name="leaflet_css"
    )
    root.header.add_child(Element(f"<script>{_vendor('leaflet.js')}</script>"), name="leaflet_js")
    root.header.add_child(Element(f"<title>{html.escape(title)}</title>"), name="title")
    payload = json.dumps(data, allow_nan=False, separators=(",", ":"))
    script = _SCRIPT % {
        "map": fmap.get_name(),
        # JSON text inside a <script> and a Jinja raw block: "</" and "{%" only occur inside JSON strings
        "data": payload.replace("</", "<\\/").replace("{%", "{\\u0025"),
        "range": f"{APS_RANGE_DB:g}",
        "changed": "#e31a1c",
        "cell": "#1f4e9c",
        "covered": COVERED,
        "uncovered": NOT_COVERED,
    }
    macro = MacroElement()
    macro._template = Template("{% macro script(this, kwargs) %}{% raw %}" + script + "{% endraw %}{% endmacro %}")
    fmap.add_child(macro)
    text = root.render()
    loads = re.search(
        r"<(?:script|img|iframe)[^>]+src=[\"']?(?:https?:)?//|<link[^>]+href=[\"']?(?:https?:)?//|url\((?:[\"']?)(?:https?:)?//|@import",
        text,
    )
    if loads is not None:
        raise DataError(f"the HTML map would load {loads.group(0)!r}: a network asset slipped in; nothing was written.")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path
