"""``write_layers``: every map file of one round (and its difference to a second round) into a folder."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rflscm.errors import ConfigError
from rflscm.eval.cache import APSCache
from rflscm.maps.crs import MapFrame
from rflscm.maps.layers import RoundLayers, round_layers
from rflscm.maps.raster import Band, Lattice, write_geotiff
from rflscm.maps.vector import (
    cell_rows,
    feature_collection,
    grid_table,
    measured_rows,
    point_feature,
    polygon_feature,
    square,
    wedge,
    wedge_radius,
    write_geojson,
    write_kml,
)
from rflscm.network.kpi import KPIConfig

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.models.source import APSSource


@dataclass
class MapOutputs:
    """What :func:`write_layers` wrote, and the layers it computed."""

    files: list[Path]
    layers: list[RoundLayers]
    frame: MapFrame
    lattice: Lattice


def grid_properties(layers: list[RoundLayers]) -> dict[str, np.ndarray]:
    """Per-grid KPI columns of every round and carrier (``r{round}_{carrier}_…``) and, for two rounds, the
    differences (``diff_{carrier}_…``: second round − first)."""
    cols: dict[str, np.ndarray] = {}
    for lay in layers:
        for c in lay.carriers:
            p = f"r{lay.round}_{c.key}_"
            cols[p + "rsrp_dbm"] = c.rsrp_dbm
            cols[p + "serving_cell"] = c.serving
            cols[p + "sinr_db"] = c.sinr_db
            cols[p + "covered"] = c.covered
    if len(layers) == 2:
        for a, b in zip(layers[0].carriers, layers[1].carriers, strict=True):
            p = f"diff_{a.key}_"
            cols[p + "rsrp_db"] = b.rsrp_dbm - a.rsrp_dbm
            cols[p + "sinr_db"] = b.sinr_db - a.sinr_db
            cols[p + "covered"] = b.covered - a.covered
            changed = np.where((a.serving >= 0) & (b.serving >= 0), (a.serving != b.serving).astype(float), np.nan)
            cols[p + "serving_changed"] = changed
    return cols


def _rasters(out: Path, lattice: Lattice, frame: MapFrame, layers: list[RoundLayers]) -> list[Path]:
    files = []
    for lay in layers:
        r, t = lay.round, lay.threshold_dbm
        cs = lay.carriers
        files += [
            write_geotiff(
                out / f"rsrp_round{r}.tif",
                lattice,
                frame,
                [Band(c.rsrp_dbm, c.label) for c in cs],
                "float32",
                float("nan"),
                "dBm",
                f"round {r}: best-server SSB RSRP (dBm), one band per carrier",
            ),
            write_geotiff(
                out / f"serving_cell_round{r}.tif",
                lattice,
                frame,
                [Band(c.serving, c.label) for c in cs],
                "int32",
                -1,
                "cell id",
                f"round {r}: serving cell id (−1: none), one band per carrier",
            ),
            write_geotiff(
                out / f"sinr_round{r}.tif",
                lattice,
                frame,
                [Band(c.sinr_db, c.label) for c in cs],
                "float32",
                float("nan"),
                "dB",
                f"round {r}: SS-SINR of the serving cell (dB)",
            ),
            write_geotiff(
                out / f"coverage_round{r}.tif",
                lattice,
                frame,
                [Band(np.where(np.isnan(c.covered), 255, c.covered).astype(np.uint8), c.label) for c in cs],
                "uint8",
                255,
                "1 = covered",
                f"round {r}: best-server RSRP >= {t:g} dBm (1) or below (0)",
            ),
        ]
    if len(layers) == 2:
        (a, b), name = layers, f"round{layers[1].round}_minus_round{layers[0].round}"
        what = f"round {b.round} − round {a.round}"
        pairs = list(zip(a.carriers, b.carriers, strict=True))
        cov = [np.where(np.isnan(y.covered - x.covered), -128, y.covered - x.covered) for x, y in pairs]
        moved = [np.where((x.serving >= 0) & (y.serving >= 0), (x.serving != y.serving), 255) for x, y in pairs]
        files += [
            write_geotiff(
                out / f"rsrp_diff_{name}.tif",
                lattice,
                frame,
                [Band(y.rsrp_dbm - x.rsrp_dbm, x.label) for x, y in pairs],
                "float32",
                float("nan"),
                "dB",
                f"{what}: best-server SSB RSRP difference (dB)",
            ),
            write_geotiff(
                out / f"sinr_diff_{name}.tif",
                lattice,
                frame,
                [Band(y.sinr_db - x.sinr_db, x.label) for x, y in pairs],
                "float32",
                float("nan"),
                "dB",
                f"{what}: SS-SINR difference (dB)",
            ),
            write_geotiff(
                out / f"coverage_diff_{name}.tif",
                lattice,
                frame,
                [Band(v.astype(np.int8), x.label) for v, (x, _) in zip(cov, pairs, strict=True)],
                "int8",
                -128,
                "+1 gained, -1 lost",
                f"{what}: coverage gained (+1), lost (−1), unchanged (0)",
            ),
            write_geotiff(
                out / f"serving_changed_{name}.tif",
                lattice,
                frame,
                [Band(v.astype(np.uint8), x.label) for v, (x, _) in zip(moved, pairs, strict=True)],
                "uint8",
                255,
                "1 = changed",
                f"{what}: serving cell changed (1) or not (0)",
            ),
        ]
    return files


def write_layers(
    source: APSSource,
    scenario: Scenario,
    out: Path,
    round: int,
    compare_round: int | None = None,
    kpi: KPIConfig | None = None,
    html: bool = True,
    title: str | None = None,
) -> MapOutputs:
    """Write GeoTIFF rasters, GeoJSON, KML and (``html``) the interactive HTML map of ``round`` (and, with
    ``compare_round``, of that round and the difference) into the folder ``out``; docs/maps.md lists the files.

    ``source`` is a fitted model (or an :class:`APSCache` of one, to share rendered APS with other work)."""
    for r, option in ((round, "--round"), (compare_round, "--compare-round")):
        if r is not None and r not in scenario.cells:
            known = ", ".join(map(str, scenario.rounds()))
            raise ConfigError(f"{option} {r}: scenario {scenario.meta.name!r} has rounds {known}.")
    if compare_round == round:
        raise ConfigError(f"--compare-round {compare_round} is --round itself; give another round to compare with.")
    kpi = kpi or KPIConfig()
    cache = APSCache.of(source)
    rounds = [round] if compare_round is None else [round, compare_round]
    layers = [round_layers(cache, scenario, r, kpi) for r in rounds]
    frame = MapFrame.of(scenario.meta.origin)
    grids = grid_table(scenario, frame)
    lattice = Lattice.of(grids[["x", "y"]].to_numpy())
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = _rasters(out, lattice, frame, layers)

    cols = grid_properties(layers)
    base = grids.to_dict("records")
    grid_rows = [dict(row, **{k: v[i] for k, v in cols.items()}) for i, row in enumerate(base)]
    features = [polygon_feature(frame, square(r["x"], r["y"], lattice.size_m), r) for r in grid_rows]
    coll = feature_collection(frame, features, f"{scenario.meta.name}: grids, KPIs of round(s) {rounds}")
    coll["pixel_size_m"] = lattice.size_m
    coll["pairs"] = layers[0].pairs
    coll["threshold_dbm"] = kpi.threshold_dbm
    files.append(write_geojson(out / "grids.geojson", coll))

    before, after = (round, compare_round) if compare_round is not None else ((1, round) if round != 1 else (1, None))
    cells = cell_rows(scenario, before, after)
    radius = [wedge_radius(scenario, c) for c in cells]
    wedges = [
        polygon_feature(frame, wedge(c["x"], c["y"], c["azimuth_deg"], r), c)  # type: ignore[arg-type]
        for c, r in zip(cells, radius, strict=True)
    ]
    files.append(write_geojson(out / "cells.geojson", feature_collection(frame, wedges, "cells (sector wedges)")))
    measured = [row for r in rounds for row in measured_rows(scenario, r)]
    points = [point_feature(frame, p["x"], p["y"], p) for p in measured]  # type: ignore[arg-type]
    files.append(write_geojson(out / "measured.geojson", feature_collection(frame, points, "measured grids")))

    folders = []
    for lay in layers:
        for c in lay.carriers:
            p = f"r{lay.round}_{c.key}_"
            rows = [
                dict(row, **{k[len(p) :]: v[i] for k, v in cols.items() if k.startswith(p)})
                for i, row in enumerate(base)
            ]
            folders.append((f"round {lay.round} · {c.label} · best-server SSB RSRP (dBm)", rows, c.rsrp_dbm, p))
    title = title or f"{scenario.meta.name}: round {' vs '.join(map(str, rounds))}"
    files.append(write_kml(out / "map.kml", frame, title, folders, lattice.size_m, cells, radius, measured))
    outputs = MapOutputs(files, layers, frame, lattice)
    if html:
        from rflscm.maps.html import write_html

        files.append(write_html(out / "map.html", cache, scenario, outputs, grids, cells, radius, measured, title))
    return outputs
