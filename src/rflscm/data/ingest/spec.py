"""What ``rflscm import`` reads: the import spec (``import.yaml`` or CLI flags) and the column names.

An import spec is a YAML mapping (every key optional except ``samples``, ``cells`` and ``codebooks``)::

    name: my-network
    samples: samples.csv                 # or a list of files; CSV or Parquet
    cells: cells.csv                     # one table (optional `round` column) or {1: r1.csv, 2: r2.csv}
    codebooks: {ssb8: {type: ssb, ...}}  # as in scenario.yaml (or a YAML file holding that mapping)
    columns: {lat: Latitude, pci: PCI}   # rflscm name: your column name (both tables)
    cell_defaults: {ssb_codebook: ssb8}  # a value for a column the cell list lacks
    origin: {lat: 48.14, lon: 11.57}     # default: the centroid of the cells
    grid_size_m: 10.0
    ...

Paths are relative to the YAML file.  See docs/your-own-data.md for every key.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd

from rflscm.config import from_dict, load_yaml
from rflscm.errors import ConfigError

SAMPLE_COLUMNS = (
    "time",
    "lat",
    "lon",
    "x",
    "y",
    "height_m",
    "cell_id",
    "pci",
    "freq_hz",
    "freq_mhz",
    "nr_arfcn",
    "earfcn",
    "beam_type",
    "beam_id",
    "rsrp_dbm",
    "round",
)
"""rflscm's names of the sample columns (see docs/your-own-data.md)."""
CELL_LIST_COLUMNS = (
    "cell_id",
    "site_id",
    "lat",
    "lon",
    "x",
    "y",
    "height_m",
    "azimuth_deg",
    "mech_tilt_deg",
    "elec_tilt_deg",
    "freq_hz",
    "freq_mhz",
    "nr_arfcn",
    "earfcn",
    "pci",
    "tx_power_dbm",
    "array_nh",
    "array_nv",
    "spacing_h_m",
    "spacing_v_m",
    "ssb_codebook",
    "csi_codebook",
    "element",
    "round",
)
"""rflscm's names of the cell-list columns."""
CARRIER_COLUMNS = ("freq_hz", "freq_mhz", "nr_arfcn", "earfcn")

ALIASES = {
    "timestamp": "time",
    "datetime": "time",
    "latitude": "lat",
    "longitude": "lon",
    "lng": "lon",
    "long": "lon",
    "height": "height_m",
    "heightaglm": "height_m",
    "heightagl": "height_m",
    "antennaheight": "height_m",
    "cell": "cell_id",
    "cellid": "cell_id",
    "cellname": "cell_id",
    "site": "site_id",
    "siteid": "site_id",
    "sitename": "site_id",
    "physicalcellid": "pci",
    "nrarfcn": "nr_arfcn",
    "ssbindex": "beam_id",
    "ssbidx": "beam_id",
    "beamindex": "beam_id",
    "beamid": "beam_id",
    "beam": "beam_id",
    "beamtype": "beam_type",
    "rsrp": "rsrp_dbm",
    "rsrpdbm": "rsrp_dbm",
    "ssrsrp": "rsrp_dbm",
    "ssrsrpdbm": "rsrp_dbm",
    "azimuth": "azimuth_deg",
    "mtilt": "mech_tilt_deg",
    "mechtilt": "mech_tilt_deg",
    "mechanicaltilt": "mech_tilt_deg",
    "etilt": "elec_tilt_deg",
    "electilt": "elec_tilt_deg",
    "electricaltilt": "elec_tilt_deg",
    "antenna": "element",
    "pattern": "element",
    "txpower": "tx_power_dbm",
    "rspower": "tx_power_dbm",
}
"""Common spellings (lower case, letters and digits only) → rflscm names, applied when no `columns:` entry says
otherwise; a bare ``freq`` or ``arfcn`` is ambiguous and must be mapped (``--col freq_mhz=freq``)."""


def _key(name: str) -> str:
    return re.sub(r"[^a-z0-9]", "", name.lower())


@dataclass(frozen=True)
class ImportSpec:
    """Settings of one import (keys of ``import.yaml``; CLI flags override them)."""

    samples: tuple[str, ...] = ()
    """Sample files (CSV or Parquet)."""
    cells: dict[int, str] = field(default_factory=dict)
    """Cell list: ``{0: file}`` for one table (a ``round`` column, or the same cells in every round) or one
    file per round ``{1: file, 2: file}``."""
    codebooks: dict[str, Any] = field(default_factory=dict)
    """Named codebooks, exactly as in scenario.yaml ``codebooks:``."""
    name: str = "imported"
    description: str = ""
    columns: dict[str, Any] = field(default_factory=dict)
    """rflscm column name → the name in your files (applies to samples and cell list); entries under ``samples:``
    or ``cells:`` apply to that table only (and win), e.g. ``{samples: {cell_id: Serving}, cells: {cell_id: Cell}}``."""
    cell_defaults: dict[str, Any] = field(default_factory=dict)
    """Values for cell-list columns the files lack (e.g. ``ssb_codebook: ssb8``, ``array_nh: 8``)."""
    origin: dict[str, float] | None = None
    """``{lat, lon[, height_m]}`` of the local frame; default: the centroid of the cells (lat/lon inputs)."""
    grid_size_m: float = 10.0
    """Side of the square grids [m]; grid (i, j) covers [i·s, (i+1)·s) × [j·s, (j+1)·s) around the origin."""
    ue_height_m: float = 1.5
    """UE height [m] where the samples have no ``height_m``."""
    beam_type: str | None = None
    """Beam type of every sample when the samples have no ``beam_type`` column (``ssb`` or ``csi``)."""
    min_samples: int = 3
    """A (round, cell, grid, beam) bin needs at least this many samples (after outliers) to be kept."""
    outlier_k: float = 3.0
    """A sample more than k · 1.4826 · MAD from its bin's median [dB] is an outlier (0: keep all)."""
    max_distance_m: float = 10_000.0
    """(PCI, carrier) resolves to the nearest such cell within this 2D distance of the sample [m]."""
    ambiguity_ratio: float = 2.0
    """…unless a second such cell lies within the limit and less than this many times as far (ambiguous)."""
    rsrp_threshold_dbm: float | None = None
    """Reporting threshold; bins averaging below it are dropped (counted).  Default: −120 dBm, or the weakest
    kept bin rounded down to a whole dB when that is lower (then nothing is dropped for it)."""
    reporting: dict[str, Any] = field(default_factory=dict)
    """The reporting rule per beam type, as in scenario.yaml ``reporting:`` (checked against the data)."""
    round_times: dict[int, tuple[str, str]] = field(default_factory=dict)
    """Rounds from time ranges ``{round: [start, end)}`` (ISO times) when the samples have no ``round``."""
    point_cloud: str | None = None
    """A point cloud to copy into the scenario (.ply, .las, .laz, .npy), in the frame of the origin."""
    terrain: str | None = None
    """A DEM GeoTIFF or XYZ table (:mod:`rflscm.data.terrain`): heights of cells and samples are above it."""

    def __post_init__(self) -> None:
        if not self.samples:
            raise ConfigError("import: no sample files; give `samples:` in the spec or --samples FILE.")
        if not self.cells:
            raise ConfigError("import: no cell list; give `cells:` in the spec or --cells FILE.")
        if not self.codebooks:
            raise ConfigError("import: no codebooks; give `codebooks:` (as in scenario.yaml) or --codebooks FILE.")
        if not self.grid_size_m > 0:
            raise ConfigError(f"import: `grid_size_m` must be > 0 m (got {self.grid_size_m}).")
        if self.min_samples < 1:
            raise ConfigError(f"import: `min_samples` must be >= 1 (got {self.min_samples}).")
        if self.outlier_k < 0 or self.max_distance_m <= 0 or self.ambiguity_ratio < 1:
            raise ConfigError("import: need `outlier_k` >= 0, `max_distance_m` > 0 and `ambiguity_ratio` >= 1.")
        if self.beam_type not in (None, "ssb", "csi"):
            raise ConfigError(f"import: `beam_type` must be ssb or csi (got {self.beam_type!r}).")
        check_columns(self.columns, "import: `columns`")


TABLE_COLUMNS = {"samples": SAMPLE_COLUMNS, "cells": CELL_LIST_COLUMNS}
"""The tables a ``columns:`` section may name, with their rflscm column names."""


def check_columns(columns: dict[str, Any], where: str) -> None:
    """A ``columns:`` mapping: rflscm name → your name (text), or ``samples:``/``cells:`` → such a mapping."""
    for key, value in columns.items():
        valid = TABLE_COLUMNS.get(key, (*SAMPLE_COLUMNS, *CELL_LIST_COLUMNS))
        inner = value if key in TABLE_COLUMNS and isinstance(value, dict) else {key: value}
        place = f"{where}.{key}" if key in TABLE_COLUMNS else where
        for name, raw in inner.items():
            if name not in valid:
                raise ConfigError(
                    f"{place}: unknown rflscm column name {name!r}; valid: {', '.join(sorted(set(valid)))}."
                )
            if not isinstance(raw, str) or not raw:
                raise ConfigError(f"{place}: `{name}` must be the name of your column (text), got {raw!r}.")


def _paths(value: Any, base: Path) -> Any:
    if isinstance(value, (list, tuple)):
        return [str(base / str(v)) for v in value]
    return str(base / str(value))


def load_spec(path: str | Path | None, overrides: dict[str, Any]) -> ImportSpec:
    """The spec from ``path`` (None: none) with ``overrides`` (CLI flags, paths as given; not changed) on top."""
    overrides = dict(overrides)
    data: dict[str, Any] = {}
    if path is not None:
        path = Path(path)
        data = load_yaml(path)
        base = path.parent
        for key in ("samples", "point_cloud", "terrain"):
            if data.get(key) is not None:
                data[key] = _paths(data[key], base)
        if isinstance(data.get("cells"), dict):
            data["cells"] = {r: _paths(f, base) for r, f in data["cells"].items()}
        elif data.get("cells") is not None:
            data["cells"] = _paths(data["cells"], base)
        if isinstance(data.get("codebooks"), str):
            data["codebooks"] = str(base / data["codebooks"])
    columns = {**(data.pop("columns", None) or {}), **overrides.pop("columns", {})}
    data.update({k: v for k, v in overrides.items() if v is not None})
    data["columns"] = columns
    if isinstance(data.get("samples"), str):
        data["samples"] = [data["samples"]]
    cells = data.get("cells")
    if isinstance(cells, str):
        data["cells"] = {0: cells}
    elif isinstance(cells, (list, tuple)):
        data["cells"] = {0: cells[0]} if len(cells) == 1 else {i + 1: c for i, c in enumerate(cells)}
    if isinstance(data.get("codebooks"), str):
        books = load_yaml(data["codebooks"])
        data["codebooks"] = books.get("codebooks", books)
    where = f"{path}: " if path is not None else ""
    try:
        return from_dict(ImportSpec, data, prefix="")
    except ConfigError as exc:
        raise ConfigError(f"{where}{exc}") from None


PLAIN_UNITS = {"", "deg", "degree", "degrees", "wgs84", "m", "metre", "meter", "metres", "meters", "dbm", "utc"}
"""Bracketed units (keys) that may be left out of a column name: those rflscm's columns are in (``Height (m)``
matches ``height_m``; ``Height (ft)`` matches nothing, so feet are never read as metres)."""


def _unit_dropped(name: str) -> str:
    """The key of ``name`` without a bracketed unit of :data:`PLAIN_UNITS` ("" when it has none)."""
    units = re.findall(r"[(\[](.*?)[)\]]", name)
    if not units or any(_key(u) not in PLAIN_UNITS for u in units):
        return ""
    return _key(re.sub(r"[(\[].*?[)\]]", "", name))


def _match(key: str, known: tuple[str, ...]) -> str | None:
    """The rflscm name whose key is ``key``, else its alias (None: none)."""
    if not key:
        return None
    return next((k for k in known if _key(k) == key), None) or ALIASES.get(key)


def canonical(df: pd.DataFrame, spec: ImportSpec, table: str) -> pd.DataFrame:
    """``df`` (a ``samples`` or ``cells`` table) with its columns renamed to rflscm names: ``spec.columns`` first
    (the table's own section over the shared entries; an entry naming a column ``df`` lacks is for the other
    table), then :data:`ALIASES` and case/spelling-insensitive matches of the known names, also with a unit in
    brackets left out (``Latitude (deg)``, ``RSRP [dBm]``); other columns are left as they are (ignored)."""
    known = TABLE_COLUMNS[table]
    mapping = {k: v for k, v in spec.columns.items() if k not in TABLE_COLUMNS}
    mapping.update(spec.columns.get(table) or {})
    by_raw = {raw: name for name, raw in mapping.items() if name in known and raw in df.columns}
    rename: dict[str, str] = {}
    taken = set(by_raw.values())
    for col in map(str, df.columns):
        if col in by_raw:
            rename[col] = by_raw[col]
            continue
        name = _match(_key(col), known) or _match(_unit_dropped(col), known)
        if name in known and name not in taken and name not in rename.values():
            rename[col] = name
    out = df.rename(columns=rename)
    return out.loc[:, ~out.columns.duplicated()]
