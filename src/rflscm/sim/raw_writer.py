"""A simulated scenario → raw samples and a planning tool's cell list, as a real network would give them.

Every reported (round, cell, grid, beam) value becomes ``samples_per_beam`` samples: the UE position is
drawn uniformly inside the grid's square (grids are ``grid_size_m`` squares centred on the grid points),
and each sample's power is the grid's value times one log-normal fading draw with σ = ``fading_db`` and
unit linear mean, so the linear-power mean over the samples tends to the grid's value.  Positions are
written as WGS84 lat/lon from ``origin``; cells as lat/lon, antenna height above (flat) ground, PCI and
NR-ARFCN (TS 38.104).  The scenario's point cloud is written beside them (``point_cloud.*``, already in the frame
of ``origin``: the scenario's own) and named in ``import.yaml``, so that the import has what the default RF-LSCM
needs.  ``rflscm import`` on the files written gives the scenario back (tested).
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from rflscm.config import to_dict
from rflscm.data import Scenario, write_table
from rflscm.data.geo import Origin, enu_to_geodetic
from rflscm.data.ingest.arfcn import hz_to_nr_arfcn, nr_arfcn_to_hz
from rflscm.data.meta import RSRP_MAX_DBM, RSRP_MIN_DBM
from rflscm.data.pointcloud import POINT_CLOUD_SUFFIXES, write_point_cloud
from rflscm.errors import ConfigError

DEFAULT_ORIGIN = Origin(48.1400, 11.5700)
"""Where simulated scenarios without an origin are placed on the globe (central Munich)."""
START = pd.Timestamp("2024-05-01T08:00:00Z")
"""Round r's samples are taken on day r − 1 after this time, one second apart."""
CLOUD_FORMATS = ("same", "none", *(s[1:] for s in POINT_CLOUD_SUFFIXES))
"""How the point cloud is written: ``same`` (the scenario's file, copied), ``none``, or a format (``laz``: ~4×
smaller than PLY, 1 mm steps)."""

CELL_COLUMNS = (
    "round",
    "cell_id",
    "site_id",
    "lat",
    "lon",
    "height_m",
    "azimuth_deg",
    "mech_tilt_deg",
    "elec_tilt_deg",
    "nr_arfcn",
    "freq_mhz",
    "pci",
    "tx_power_dbm",
    "array_nh",
    "array_nv",
    "spacing_h_m",
    "spacing_v_m",
    "ssb_codebook",
    "csi_codebook",
    "element",
)


def write_raw(
    scenario: Scenario,
    out: Path,
    origin: Origin | None = None,
    samples_per_beam: int = 5,
    fading_db: float = 2.0,
    grid_size_m: float = 10.0,
    max_grids: int | None = None,
    seed: int = 0,
    point_cloud: str = "same",
) -> dict[str, Any]:
    """Write ``samples.csv``, ``cells.csv``, ``import.yaml`` and the point cloud into ``out``; returns a summary.

    Args:
        origin: where the frame's (0, 0, 0) lies (default: the scenario's, else :data:`DEFAULT_ORIGIN`).
        max_grids: keep only this many grids (evenly spread over the sorted grid ids) for a small file.
        point_cloud: one of :data:`CLOUD_FORMATS`.
    """
    if samples_per_beam < 1 or fading_db < 0 or grid_size_m <= 0:
        raise ConfigError("raw samples need samples_per_beam >= 1, fading_db >= 0 and grid_size_m > 0.")
    if point_cloud not in CLOUD_FORMATS:
        raise ConfigError(f"raw point cloud format must be one of {', '.join(CLOUD_FORMATS)} (got {point_cloud!r}).")
    origin = origin or scenario.meta.origin or DEFAULT_ORIGIN
    rng = np.random.default_rng(seed)
    out.mkdir(parents=True, exist_ok=True)
    m = scenario.measurements
    m = m[m["rsrp_dbm"].notna().to_numpy()]
    if max_grids is not None:
        ids = np.sort(scenario.grid_ids())
        chosen = ids[np.unique(np.linspace(0, len(ids) - 1, min(max_grids, len(ids))).astype(int))]
        m = m[m["grid_id"].isin(chosen).to_numpy()]
    m = m.sort_values(["round", "grid_id", "cell_id", "beam_type", "beam_id"], kind="stable")
    cells = _cells(scenario, origin)
    samples = _samples(scenario, m, cells, origin, samples_per_beam, fading_db, grid_size_m, rng)
    write_table(samples, out / "samples.csv")
    write_table(cells, out / "cells.csv")
    spec = {
        "name": f"{scenario.meta.name}-imported",
        "samples": "samples.csv",
        "cells": "cells.csv",
        "origin": to_dict(origin),
        "grid_size_m": grid_size_m,
        "rsrp_threshold_dbm": None,
        "reporting": {k: r.to_dict() for k, r in scenario.meta.reporting.items()},
        "codebooks": {name: to_dict(cb) for name, cb in scenario.meta.codebooks.items()},
    }
    cloud = _write_cloud(scenario, out, point_cloud)
    if cloud is not None:
        spec["point_cloud"] = cloud
    text = "# written by rflscm simulate --raw-out; import with `rflscm import import.yaml --out DIR`\n"
    (out / "import.yaml").write_text(text + yaml.safe_dump(spec, sort_keys=False, default_flow_style=None))
    points = 0 if cloud is None or scenario.point_cloud is None else scenario.point_cloud.num_points
    return {"samples": len(samples), "cells": len(cells), "grids": int(m["grid_id"].nunique()), "cloud_points": points}


def _write_cloud(scenario: Scenario, out: Path, how: str) -> str | None:
    """The scenario's point cloud as ``out/point_cloud.<ext>`` (its file copied for ``same``); its name or None."""
    if scenario.point_cloud is None or how == "none":
        return None
    source = scenario.root / scenario.meta.point_cloud if scenario.meta.point_cloud else None
    if how == "same" and source is not None and source.is_file():
        name = "point_cloud" + source.suffix.lower()
        shutil.copyfile(source, out / name)
        return name
    name = "point_cloud." + ("ply" if how == "same" else how)
    write_point_cloud(scenario.point_cloud, out / name)
    return name


def _cells(scenario: Scenario, origin: Origin) -> pd.DataFrame:
    parts = []
    for rnd, table in sorted(scenario.cells.items()):
        lat, lon, _ = enu_to_geodetic(table[["x", "y", "z"]].to_numpy(np.float64), origin)
        part = table.assign(round=rnd, lat=lat, lon=lon, height_m=table["z"].to_numpy())
        freq = scenario.cells[1]["freq_hz"].to_numpy()
        if np.array_equal(nr_arfcn_to_hz(hz_to_nr_arfcn(freq)), freq):  # on the NR global raster
            part["nr_arfcn"] = hz_to_nr_arfcn(table["freq_hz"].to_numpy())
        else:  # e.g. 3.5 GHz lies between two 15 kHz raster points: MHz keeps it exact
            part["freq_mhz"] = table["freq_hz"].to_numpy() / 1e6
        part["pci"] = np.arange(len(table)) % 1008
        parts.append(part[[c for c in CELL_COLUMNS if c in part.columns]])
    return pd.concat(parts, ignore_index=True)


def _samples(
    scenario: Scenario,
    m: pd.DataFrame,
    cells: pd.DataFrame,
    origin: Origin,
    n: int,
    fading_db: float,
    grid_size_m: float,
    rng: np.random.Generator,
) -> pd.DataFrame:
    rep = np.repeat(np.arange(len(m)), n)
    rows = m.iloc[rep]
    grid = scenario.grids.set_index("grid_id").loc[rows["grid_id"].to_numpy()]
    jitter = rng.uniform(-0.49, 0.49, size=(len(rows), 2)) * grid_size_m  # strictly inside the square
    xyz = np.stack([grid["x"].to_numpy() + jitter[:, 0], grid["y"].to_numpy() + jitter[:, 1], grid["z"].to_numpy()], -1)
    lat, lon, height = enu_to_geodetic(xyz, origin)
    mu = -(fading_db**2) * np.log(10.0) / 20.0  # E[10^(g/10)] = 1 for g ~ N(mu, σ²) [dB]
    rsrp = rows["rsrp_dbm"].to_numpy() + rng.normal(mu, fading_db, len(rows))
    rsrp = np.clip(rsrp, RSRP_MIN_DBM, RSRP_MAX_DBM)
    key = cells.set_index(["round", "cell_id"])
    at = pd.MultiIndex.from_arrays([rows["round"].to_numpy(), rows["cell_id"].to_numpy()])
    rnd = rows["round"].to_numpy()
    report = pd.factorize(pd.MultiIndex.from_frame(rows[["round", "grid_id", "cell_id", "beam_type"]]))[0]
    seconds = report * n + np.arange(len(rows)) % n  # the beams of one report share its n times, 1 s apart
    seconds = seconds - seconds[np.searchsorted(rnd, rnd)]  # each round starts at its day's START
    time = START + pd.to_timedelta(rnd - 1, unit="D") + pd.to_timedelta(seconds, unit="s")
    carrier = "nr_arfcn" if "nr_arfcn" in cells.columns else "freq_mhz"
    return pd.DataFrame(
        {
            "time": time.strftime("%Y-%m-%dT%H:%M:%SZ"),
            "lat": lat,
            "lon": lon,
            "height_m": height,
            "pci": key["pci"].reindex(at).to_numpy(),
            carrier: key[carrier].reindex(at).to_numpy(),
            "beam_type": rows["beam_type"].to_numpy(),
            "beam_index": rows["beam_id"].to_numpy(),
            "rsrp_dbm": np.round(rsrp, 2),
            "round": rnd,
        }
    )
