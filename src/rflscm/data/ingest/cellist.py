"""A planning tool's cell list → the scenario's cells tables (one per round), with PCI and carrier kept aside.

Columns (rflscm names; map yours with ``columns:``): ``cell_id`` (a number or a name), ``site_id``
(default: one site per distinct position), ``lat``/``lon`` (WGS84) or ``x``/``y`` [m], ``height_m`` (antenna
height above ground [m]; without a terrain model the ground is flat at the origin's height), ``azimuth_deg``,
``mech_tilt_deg``, ``elec_tilt_deg``, the carrier as ``freq_hz``, ``freq_mhz``, ``nr_arfcn`` or ``earfcn``,
``pci``, and optionally ``tx_power_dbm``, ``array_nh``, ``array_nv``, ``spacing_h_m``, ``spacing_v_m``,
``ssb_codebook``, ``csi_codebook``, ``element`` (``tr38901`` or a pattern file next to the cell list) and
``round``.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd

from rflscm.antenna.msi import read_msi
from rflscm.data.cells import BAND_TOLERANCE, off_band
from rflscm.data.columns import TableRef, float_column, int_column, raise_rows, require_columns, str_column
from rflscm.data.geo import Origin, geodetic_to_enu
from rflscm.data.ingest.arfcn import earfcn_to_hz, nr_arfcn_to_hz
from rflscm.data.ingest.spec import CARRIER_COLUMNS, ImportSpec, canonical
from rflscm.data.io import read_table
from rflscm.errors import DataError

NO_PCI = -1
"""``pci`` of the cells of a list without a ``pci`` column (samples must then name cells by ``cell_id``)."""
PASS_THROUGH = (
    "azimuth_deg",
    "mech_tilt_deg",
    "elec_tilt_deg",
    "tx_power_dbm",
    "array_nh",
    "array_nv",
    "spacing_h_m",
    "spacing_v_m",
    "ssb_codebook",
    "csi_codebook",
    "element",
)


def carrier_hz(df: pd.DataFrame, ref: TableRef) -> np.ndarray:
    """Carrier [Hz] ``[num_rows]`` from whichever of ``freq_hz``, ``freq_mhz``, ``nr_arfcn``, ``earfcn`` is given."""
    given = [c for c in CARRIER_COLUMNS if c in df.columns]
    if len(given) != 1:
        what = "none" if not given else ", ".join(given)
        raise DataError(
            f"{ref.name}: give the carrier in exactly one column of freq_hz, freq_mhz, nr_arfcn, earfcn (found "
            f"{what}); map yours with e.g. --col nr_arfcn=ARFCN."
        )
    col = given[0]
    raw = float_column(df, ref, col)
    if col == "freq_hz":
        hz = raw
    elif col == "freq_mhz":
        hz = raw * 1e6
    else:
        hz = nr_arfcn_to_hz(raw) if col == "nr_arfcn" else earfcn_to_hz(raw)
        what = "NR-ARFCN (TS 38.104 §5.4.2.1)" if col == "nr_arfcn" else "EARFCN of a known LTE band (TS 36.101)"
        raise_rows(ref, np.isnan(hz), col, df[col], f"is not a valid {what}")
    raise_rows(ref, (hz < 1e8) | (hz > 1e11), col, df[col], "gives a carrier outside 0.1…100 GHz; check the unit")
    return np.round(hz, 0)


def read_cell_list(spec: ImportSpec, origin_of: Origin | None = None) -> tuple[dict[int, pd.DataFrame], list[Path]]:
    """The cell list as raw tables per round (key 0: one table, with a ``round`` column or for every round),
    canonical column names, and the files read."""
    tables: dict[int, pd.DataFrame] = {}
    for rnd, name in spec.cells.items():
        df = canonical(read_table(name), spec, "cells")
        for key, value in spec.cell_defaults.items():
            if key not in df.columns:
                df[key] = value
        df.attrs["file"] = Path(name).name
        df.attrs["folder"] = str(Path(name).parent)
        tables[int(rnd)] = df
    return tables, [Path(n) for n in spec.cells.values()]


def cell_origin(tables: dict[int, pd.DataFrame]) -> Origin | None:
    """The centroid of the cells' lat/lon (None when the list gives x/y)."""
    first = tables[min(tables)]
    if "lat" not in first.columns or "lon" not in first.columns:
        return None
    ref = TableRef(first.attrs.get("file", "cells"))
    return Origin(float(np.mean(float_column(first, ref, "lat"))), float(np.mean(float_column(first, ref, "lon"))))


def cells_frame(df: pd.DataFrame, origin: Origin | None, ids: dict[str, int]) -> pd.DataFrame:
    """A cell-list table → the scenario cells table plus ``pci``, ``carrier_hz``, ``cell_name`` (and ``round``
    when the table has one) columns; rows keep the file's order, so messages name the file's rows."""
    ref = TableRef(df.attrs.get("file", "cells"), csv=str(df.attrs.get("file", "")).lower().endswith(".csv"))
    require_columns(
        df,
        ref,
        ["cell_id", "height_m", "azimuth_deg"],
        "cell_id, lat/lon or x/y, height_m, azimuth_deg, a carrier, ssb_codebook, csi_codebook (and pci when the "
        "samples name cells by PCI)",
    )
    if {"lat", "lon"} <= set(df.columns):
        if origin is None:
            raise DataError(f"{ref.name}: gives lat/lon; the import needs an origin (--origin LAT,LON).")
        lat, lon = float_column(df, ref, "lat"), float_column(df, ref, "lon")
        raise_rows(ref, np.abs(lat) > 90, "lat", df["lat"], "is not a latitude (−90…90°)")
        xyz = geodetic_to_enu(lat, lon, np.zeros(len(df)), origin)
        x, y = xyz[:, 0], xyz[:, 1]
    else:
        require_columns(df, ref, ["x", "y"], "lat/lon (WGS84) or x/y [m]")
        x, y = float_column(df, ref, "x"), float_column(df, ref, "y")
    names = str_column(df, ref, "cell_id")
    out = pd.DataFrame({"cell_id": [ids.setdefault(n, _cell_number(n, ids)) for n in names]})
    if "site_id" in df.columns:
        out["site_id"] = pd.factorize(str_column(df, ref, "site_id"))[0] + 1
    else:
        out["site_id"] = pd.factorize(pd.Series(np.round(x, 1)).astype(str) + "," + np.round(y, 1).astype(str))[0] + 1
    out["x"], out["y"], out["z"] = x, y, float_column(df, ref, "height_m")
    for col in PASS_THROUGH:
        if col in df.columns:
            out[col] = df[col].to_numpy()
    out["carrier_hz"] = carrier_hz(df, ref)
    if "element" in df.columns:
        _check_elements(df, ref, Path(str(df.attrs.get("folder", "."))), out["carrier_hz"].to_numpy())
    out["pci"] = int_column(df, ref, "pci") if "pci" in df.columns else NO_PCI
    out["freq_hz"] = out["carrier_hz"]
    out["cell_name"] = names
    key = ["cell_id"]
    if "round" in df.columns:  # one table for every round: split by the caller
        out["round"] = int_column(df, ref, "round")
        raise_rows(ref, out["round"].to_numpy() < 1, "round", df["round"], "must be a round number >= 1")
        key = ["round", "cell_id"]
    dup = out.duplicated(key).to_numpy()
    raise_rows(ref, dup, "cell_id", names, "is listed twice in one round; list each cell once per round")
    return out


def _check_elements(df: pd.DataFrame, ref: TableRef, folder: Path, carrier: np.ndarray) -> None:
    """An ``element`` must be ``tr38901``, empty or a pattern file next to the cell list (an antenna *model name*
    is not a pattern: map the column away or give the file), measured in the band of the cell's ``carrier`` [Hz]
    (the band rule of :func:`rflscm.data.cells.off_band`)."""
    names = df["element"].astype("string").fillna("").str.strip()
    ok = names.str.lower().isin(["", "tr38901"]) | names.map(lambda n: (folder / n).is_file() if n else True)
    raise_rows(
        ref,
        ~ok.to_numpy(dtype=bool),
        "element",
        df["element"],
        f"names no pattern file next to the cell list ({folder}); give a Planet/MSI file there, `tr38901`, or "
        "leave the column out (an antenna model name is not a pattern)",
    )
    measured: dict[str, float | None] = {}
    for name in pd.unique(names[names.str.lower().ne("tr38901") & names.ne("")]):
        try:
            measured[str(name)] = read_msi(folder / str(name)).frequency_hz
        except DataError as exc:
            raise DataError(f"{ref.name}: `element` = {name!r}: {exc}") from None
    pattern_hz = names.map(lambda n: measured.get(n)).to_numpy(dtype=object)
    off = np.array([off_band(p, float(c)) for p, c in zip(pattern_hz, carrier, strict=True)], dtype=bool)
    if off.any():
        i = int(np.flatnonzero(off)[0])
        raise_rows(
            ref,
            off,
            "element",
            df["element"],
            f"is measured at {pattern_hz[i] / 1e6:g} MHz, but this cell's carrier is {carrier[i] / 1e6:g} MHz "
            f"(beyond ±{100 * BAND_TOLERANCE:g} %); give the pattern of this band",
        )


def _cell_number(name: str, ids: dict[str, int]) -> int:
    """A cell's number: the name itself when it is a whole number not taken by another name (``007`` after
    ``7``), else the next free number."""
    used = set(ids.values())
    if name.lstrip("-").isdigit() and int(name) not in used:
        return int(name)
    return max(used | {-1}) + 1


def copy_elements(cells: pd.DataFrame, folder: str, out: Path) -> None:
    """Copy the pattern files the ``element`` column names (relative to the cell list) into the scenario."""
    if "element" not in cells.columns:
        return
    for name in pd.unique(cells["element"].dropna().astype(str)):
        src = Path(folder) / name
        if name != "tr38901" and src.is_file():
            (out / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src, out / name)
