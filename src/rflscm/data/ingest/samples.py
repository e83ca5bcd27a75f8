"""Raw samples → one clean long table (position, round, cell key, beam, RSRP), every dropped row counted.

Columns (rflscm names): ``time`` (ISO time, needed for ``round_times``), ``lat``/``lon`` (WGS84) or ``x``/``y``
[m], optional ``height_m`` (UE height [m]), the cell as ``cell_id`` or as ``pci`` with a carrier
(``freq_hz``, ``freq_mhz``, ``nr_arfcn`` or ``earfcn``), ``beam_type`` (``ssb``/``csi``; or one for all),
``beam_id`` (0-based SSB/CSI-RS resource index), ``rsrp_dbm`` and optionally ``round``.

A row without a position or without an RSRP is dropped and counted (a drive test logs such rows while
the GPS has no fix or the beam was not measured); a value that is present but not a number, an RSRP
outside −156…−31 dBm or an unknown beam type stops the import naming the file, row and value.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from rflscm.data.columns import TableRef, float_column, int_column, raise_rows, require_columns, str_column
from rflscm.data.geo import Origin, geodetic_to_enu
from rflscm.data.ingest.cellist import carrier_hz
from rflscm.data.ingest.spec import CARRIER_COLUMNS, ImportSpec, canonical
from rflscm.data.io import LINE_NUMBERS, read_table
from rflscm.data.meta import RSRP_MAX_DBM, RSRP_MIN_DBM
from rflscm.data.reporting import BEAM_TYPES
from rflscm.errors import DataError


class Tally:
    """Dropped samples (and bins) per reason, in the order the reasons first occurred."""

    def __init__(self) -> None:
        self.samples: dict[str, int] = {}
        self.bins: dict[str, int] = {}

    def drop(self, reason: str, samples: int, bins: int = 0) -> None:
        if samples or bins:
            self.samples[reason] = self.samples.get(reason, 0) + int(samples)
            self.bins[reason] = self.bins.get(reason, 0) + int(bins)

    @property
    def dropped(self) -> int:
        return sum(self.samples.values())


def read_samples(spec: ImportSpec, origin: Origin | None, tally: Tally) -> pd.DataFrame:
    """All sample files as one table with columns ``x, y, z, round, cell_id`` (−1: resolve by PCI), ``pci``,
    ``carrier_hz``, ``beam_type``, ``beam_id``, ``rsrp_dbm``, ``file``, ``row`` (1-based in its file)."""
    parts = [_one_file(Path(name), spec, origin, tally) for name in spec.samples]
    return pd.concat(parts, ignore_index=True)


def _one_file(path: Path, spec: ImportSpec, origin: Origin | None, tally: Tally) -> pd.DataFrame:
    raw = read_table(path)
    ref = TableRef(path.name, csv=path.suffix.lower() == ".csv", lines=raw.attrs.get(LINE_NUMBERS))
    df = canonical(raw, spec, "samples")
    geo = {"lat", "lon"} <= set(df.columns)
    require_columns(
        df,
        ref,
        ["lat", "lon"] if geo or "x" not in df.columns else ["x", "y"],
        "lat/lon (WGS84) or x/y [m], rsrp_dbm, beam_id, and cell_id or pci with a carrier",
    )
    require_columns(df, ref, ["rsrp_dbm", "beam_id"])
    a, b = (float_column(df, ref, c, allow_nan=True) for c in (("lat", "lon") if geo else ("x", "y")))
    rsrp = float_column(df, ref, "rsrp_dbm", allow_nan=True)
    no_pos, no_rsrp = np.isnan(a) | np.isnan(b), np.isnan(rsrp)
    tally.drop(f"{path.name}: no position (empty {'lat/lon' if geo else 'x/y'})", int(no_pos.sum()))
    tally.drop(f"{path.name}: no RSRP (empty rsrp_dbm)", int((no_rsrp & ~no_pos).sum()))
    keep = ~(no_pos | no_rsrp)
    df, a, b, rsrp = df[keep], a[keep], b[keep], rsrp[keep]
    rows = np.flatnonzero(keep)
    ref = TableRef(ref.name, ref.csv, None if ref.lines is None else np.asarray(ref.lines)[rows])
    bad = (rsrp < RSRP_MIN_DBM) | (rsrp > RSRP_MAX_DBM)
    raise_rows(
        ref,
        bad,
        "rsrp_dbm",
        df["rsrp_dbm"],
        f"is outside the reportable range {RSRP_MIN_DBM:g}…{RSRP_MAX_DBM:g} dBm (values in W or mW? convert to dBm)",
    )
    if geo:
        if origin is None:
            raise DataError(f"{path.name}: gives lat/lon; the import needs an origin (--origin LAT,LON).")
        raise_rows(ref, np.abs(a) > 90, "lat", df["lat"], "is not a latitude (−90…90°; lat and lon swapped?)")
        z0 = float_column(df, ref, "height_m", default=spec.ue_height_m)
        xyz = geodetic_to_enu(a, b, z0 + origin.height_m, origin)
    else:
        xyz = np.stack([a, b, float_column(df, ref, "height_m", default=spec.ue_height_m)], axis=-1)
    out = pd.DataFrame({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]})
    out["round"] = _rounds(df, ref, spec, tally, path.name)
    if "cell_id" in df.columns:
        out["cell_name"] = str_column(df, ref, "cell_id")
        out["pci"], out["carrier_hz"] = -1, np.nan
    else:
        require_columns(df, ref, ["pci"], "cell_id, or pci with a carrier column (freq_hz, freq_mhz, nr_arfcn, earfcn)")
        if not any(c in df.columns for c in CARRIER_COLUMNS):
            raise DataError(f"{path.name}: gives pci but no carrier; add freq_hz, freq_mhz, nr_arfcn or earfcn.")
        out["cell_name"] = ""
        out["pci"], out["carrier_hz"] = int_column(df, ref, "pci"), carrier_hz(df, ref)
    out["beam_type"] = _beam_types(df, ref, spec)
    out["beam_id"] = int_column(df, ref, "beam_id")
    raise_rows(ref, out["beam_id"].to_numpy() < 0, "beam_id", df["beam_id"], "must be >= 0 (0-based beam index)")
    out["rsrp_dbm"] = rsrp
    out["time"] = df["time"].astype(str).to_numpy() if "time" in df.columns else ""
    out["file"], out["row"] = path.name, rows + 1
    return out[out["round"].to_numpy() > 0].reset_index(drop=True)


def _beam_types(df: pd.DataFrame, ref: TableRef, spec: ImportSpec) -> np.ndarray:
    if "beam_type" not in df.columns:
        if spec.beam_type is None:
            raise DataError(f"{ref.name}: no `beam_type` column; add one (ssb/csi) or give --beam-type ssb.")
        return np.full(len(df), spec.beam_type, dtype=object)
    types = np.char.lower(str_column(df, ref, "beam_type").astype(str))
    types = np.where(np.isin(types, ("csirs", "csi-rs", "csi_rs")), "csi", types)
    raise_rows(ref, ~np.isin(types, BEAM_TYPES), "beam_type", df["beam_type"], "must be ssb or csi")
    return types.astype(object)


def _rounds(df: pd.DataFrame, ref: TableRef, spec: ImportSpec, tally: Tally, name: str) -> np.ndarray:
    """Round per row: the ``round`` column, else ``round_times`` ranges (rows outside all → 0, counted), else 1."""
    if "round" in df.columns:
        rounds = int_column(df, ref, "round")
        raise_rows(ref, rounds < 1, "round", df["round"], "must be a round number >= 1")
        return rounds
    if not spec.round_times:
        return np.ones(len(df), dtype=np.int64)
    require_columns(df, ref, ["time"], "time (ISO date and time) for `round_times`")
    times = parse_times(df["time"])
    raise_rows(
        ref,
        times.isna().to_numpy(),
        "time",
        df["time"],
        "is not a date and time (ISO 8601, e.g. 2024-05-01T10:00:00Z, or Unix seconds)",
    )
    rounds = np.zeros(len(df), dtype=np.int64)
    for rnd, (start, end) in sorted(spec.round_times.items()):
        lo, hi = pd.Timestamp(start), pd.Timestamp(end)
        lo, hi = (t.tz_localize("UTC") if t.tzinfo is None else t for t in (lo, hi))
        inside = ((times >= lo) & (times < hi)).to_numpy()
        rounds[inside & (rounds == 0)] = int(rnd)
    tally.drop(f"{name}: time outside every round of `round_times`", int((rounds == 0).sum()))
    return rounds


EPOCH_MS_ABOVE = 1e11
"""Numeric times are Unix seconds; above this (year 5138 in seconds) they are Unix milliseconds."""


def parse_times(values: pd.Series) -> pd.Series:
    """Times [UTC] of a ``time`` column: ISO 8601 text (without a zone: UTC), or numbers = Unix seconds
    (milliseconds above :data:`EPOCH_MS_ABOVE`); NaT where a value is neither."""
    numbers = pd.to_numeric(values, errors="coerce")
    if len(values) and numbers.notna().all():
        ms = (numbers.abs() > EPOCH_MS_ABOVE).to_numpy()
        out = pd.Series(pd.NaT, index=values.index, dtype="datetime64[ns, UTC]")
        out[~ms] = pd.to_datetime(numbers[~ms], unit="s", utc=True, errors="coerce")
        out[ms] = pd.to_datetime(numbers[ms].round(), unit="ms", utc=True, errors="coerce")
        return out
    return pd.to_datetime(values.astype(str), errors="coerce", utc=True, format="ISO8601")
