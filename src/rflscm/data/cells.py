"""The cells table of a measurement round: validation, defaults and normalisation.

Columns (angles in the planning-tool convention of SPEC §2):

================  =======  =========================================================
column            unit     meaning (default when the column or a value is absent)
================  =======  =========================================================
cell_id           int      cell identifier, unique in the table
site_id           int      site identifier (co-sited cells share it)
x, y, z           m        antenna position in the ENU frame (or lat, lon, height_m)
azimuth_deg       deg      boresight azimuth, clockwise from north, 0…360
mech_tilt_deg     deg      mechanical down-tilt, positive down, −90…90
elec_tilt_deg     deg      electrical down-tilt, positive down, −90…90
freq_hz           Hz       carrier, one of scenario.yaml ``frequencies_hz``
tx_power_dbm      dBm      RS power per resource element (EPRE) (15)
array_nh          int      horizontal elements (8)
array_nv          int      vertical elements (4)
spacing_h_m       m        horizontal element spacing (0.5 λ at ``freq_hz``)
spacing_v_m       m        vertical element spacing (0.7 λ at ``freq_hz``)
ssb_codebook      text     name of a scenario.yaml codebook for the SSB beams
csi_codebook      text     name of a scenario.yaml codebook for the CSI-RS beams
element           text     ``tr38901`` (default, also when empty) or a Planet/MSI file
                           path relative to the scenario folder
================  =======  =========================================================

An empty value in an optional column takes the default.  Every round lists the
same cells at the same positions, sites and carriers; only the antenna
configuration (codebooks, angles, array, power, element) may change.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from rflscm.antenna import ArrayGeometry, ElementPattern, PatternCodebook, TR38901Element, read_msi, wavelength_of
from rflscm.data.columns import (
    TableRef,
    check_not_empty,
    check_unknown_columns,
    clean_column_names,
    duplicate_rows,
    float_column,
    fmt_list,
    fmt_number,
    fmt_value,
    int_column,
    raise_rows,
    str_column,
)
from rflscm.data.meta import ScenarioMeta, frequency_unit_hint
from rflscm.data.positions import XYZ, finish_table, known_columns, position_columns
from rflscm.errors import ConfigError, DataError

CELL_COLUMNS = tuple(
    [
        "cell_id",
        "site_id",
        "x",
        "y",
        "z",
        "azimuth_deg",
        "mech_tilt_deg",
        "elec_tilt_deg",
        "freq_hz",
        "tx_power_dbm",
        "array_nh",
        "array_nv",
        "spacing_h_m",
        "spacing_v_m",
        "ssb_codebook",
        "csi_codebook",
        "element",
    ]
)
"""Columns of a normalised cells table, in order (extra user columns follow)."""
REQUIRED = [
    "cell_id",
    "site_id",
    "azimuth_deg",
    "mech_tilt_deg",
    "elec_tilt_deg",
    "freq_hz",
    "ssb_codebook",
    "csi_codebook",
]
DEFAULT_ELEMENT = "tr38901"
TX_POWER_RANGE_DBM = (-20.0, 40.0)
"""Plausible RS power per resource element (EPRE) [dBm]: small cells ≈ 0…10, macro cells ≈ 10…25 (TS 38.104
output powers spread over the subcarriers); values outside are a unit mistake (W, mW or total power)."""
MAX_ARRAY_ELEMENTS = 4096
"""Most antenna elements of one cell (array_nh × array_nv): 64 × 64; massive-MIMO panels have a few hundred."""
MAX_SPACING_WL = 2.0
"""Element spacings above this many wavelengths are taken for a unit mistake (wavelengths given as metres)."""


def normalise_cells(
    df: pd.DataFrame, ref: TableRef, meta: ScenarioMeta, root: Path, round1: tuple[pd.DataFrame, str] | None = None
) -> tuple[pd.DataFrame, dict[str, ElementPattern]]:
    """Validate a cells table and fill its defaults.

    Args:
        df: the table as read, in file order.
        ref: its file, for messages.
        meta: scenario.yaml (carriers, codebooks, origin).
        root: the scenario folder (element pattern files are relative to it).
        round1: ``(normalised round-1 table, its file name)`` when ``df`` is a later round.

    Returns:
        ``(cells, elements)``: the table with :data:`CELL_COLUMNS` (+ extra columns) sorted by
        ``cell_id`` with a 0…n−1 index, and the element patterns read, by ``element`` value.
    """
    df = clean_column_names(df, ref)
    check_not_empty(df, ref, "one row per cell")
    xyz = position_columns(df, ref, REQUIRED, meta.origin, meta.ground)
    check_unknown_columns(df, ref, known_columns(df, CELL_COLUMNS))
    out = pd.DataFrame({"cell_id": int_column(df, ref, "cell_id"), "site_id": int_column(df, ref, "site_id")})
    out[list(XYZ)] = xyz
    _angles(df, ref, out)
    _radio(df, ref, out, meta)
    _array(df, ref, out)
    _codebooks(df, ref, out, meta)
    elements = _elements(df, ref, out, root)
    _bands(ref, out, elements, meta)
    duplicate_rows(ref, out, ["cell_id"], "list each cell once per round")
    if round1 is not None:
        _same_cells_as_round1(out, ref, *round1)
    return finish_table(out, df, ["cell_id"]), elements


def _angles(df: pd.DataFrame, ref: TableRef, out: pd.DataFrame) -> None:
    az = float_column(df, ref, "azimuth_deg")
    hint = "; add 360 to negative azimuths" if (az < 0).any() else ""
    problem = f"is outside 0…360° (clockwise from north{hint})"
    raise_rows(ref, (az < 0) | (az > 360), "azimuth_deg", df["azimuth_deg"], problem)
    out["azimuth_deg"] = az
    for name in ("mech_tilt_deg", "elec_tilt_deg"):
        tilt = float_column(df, ref, name)
        raise_rows(ref, np.abs(tilt) > 90, name, df[name], "is outside −90…90° (tilt in degrees, positive = down)")
        out[name] = tilt


def _radio(df: pd.DataFrame, ref: TableRef, out: pd.DataFrame, meta: ScenarioMeta) -> None:
    freq = float_column(df, ref, "freq_hz")
    raise_rows(ref, freq <= 0, "freq_hz", df["freq_hz"], "must be a positive carrier frequency in Hz")
    wrong_unit = freq < 1e8  # below 100 MHz: GHz, MHz or kHz given as Hz
    if wrong_unit.any():
        first = int(np.flatnonzero(wrong_unit)[0])
        raise_rows(ref, wrong_unit, "freq_hz", df["freq_hz"], str(frequency_unit_hint(freq[first])))
    carriers = np.asarray(meta.frequencies_hz, dtype=np.float64)
    match = np.abs(freq[:, None] - carriers[None, :]) <= 1e-6 * carriers[None, :]  # [num_cells, num_carriers]
    problem = (
        f"is not a carrier of scenario.yaml `frequencies_hz` ({fmt_list(fmt_number(f) for f in carriers)}); "
        "add it there or correct the value"
    )
    raise_rows(ref, np.asarray(~match.any(axis=1)), "freq_hz", df["freq_hz"], problem)
    out["freq_hz"] = carriers[np.argmax(match, axis=1)]
    power = float_column(df, ref, "tx_power_dbm", default=15.0)
    lo, hi = TX_POWER_RANGE_DBM
    problem = (
        f"is outside the plausible {lo:g}…{hi:g} dBm (the RS power per resource element, EPRE, in dBm; typically "
        "10…25; total transmit power or W/mW?)"
    )
    raise_rows(ref, (power < lo) | (power > hi), "tx_power_dbm", df.get("tx_power_dbm", power), problem)
    out["tx_power_dbm"] = power


def _array(df: pd.DataFrame, ref: TableRef, out: pd.DataFrame) -> None:
    for name, default in (("array_nh", 8), ("array_nv", 4)):
        n = int_column(df, ref, name, default=default)
        raise_rows(ref, (n < 1) | (n > 1024), name, df.get(name, n), "must be a number of elements in 1…1024")
        out[name] = n
    total = out["array_nh"].to_numpy() * out["array_nv"].to_numpy()
    problem = f"× `array_nv` is more than {MAX_ARRAY_ELEMENTS} elements (the largest array rflscm models)"
    raise_rows(ref, total > MAX_ARRAY_ELEMENTS, "array_nh", df.get("array_nh", out["array_nh"]), problem)
    wavelength = wavelength_of(1.0) / out["freq_hz"].to_numpy()  # [num_cells] m
    for name, default_wl in (("spacing_h_m", 0.5), ("spacing_v_m", 0.7)):
        spacing = float_column(df, ref, name, default=default_wl * wavelength)
        raw = df.get(name, spacing)
        raise_rows(ref, spacing <= 0, name, raw, "must be a positive element spacing in metres")
        problem = (
            f"is more than {MAX_SPACING_WL:g} wavelengths at this cell's carrier; spacing is in metres "
            "(e.g. 0.5 λ at 3.5 GHz = 0.0428 m), or leave it empty for the default"
        )
        raise_rows(ref, spacing > MAX_SPACING_WL * wavelength, name, raw, problem)
        out[name] = spacing


def _codebooks(df: pd.DataFrame, ref: TableRef, out: pd.DataFrame, meta: ScenarioMeta) -> None:
    valid = ", ".join(meta.codebooks)
    for column in ("ssb_codebook", "csi_codebook"):
        names = str_column(df, ref, column)
        known = np.isin(names, list(meta.codebooks))
        problem = f"is not a codebook of scenario.yaml `codebooks`; valid: {valid}"
        raise_rows(ref, ~known, column, df[column], problem)
        out[column] = pd.array(names, dtype="str")
        combos = pd.DataFrame({"name": names, "nh": out["array_nh"], "nv": out["array_nv"]})
        for row in combos.drop_duplicates().itertuples():  # few distinct (codebook, array) pairs
            book = meta.codebooks[row.name]
            if isinstance(book, PatternCodebook):  # measured gains: no elements to fit
                continue
            try:
                book.weights(ArrayGeometry(num_h=row.nh, num_v=row.nv), 0.1)
            except ConfigError as exc:
                raise DataError(
                    f"{ref.row(int(row.Index))}: `{column}` = {row.name!r} does not fit this cell's array: "
                    f"{str(exc).rstrip('.')}; change `array_nh`/`array_nv` or the codebook."
                ) from None


def _elements(df: pd.DataFrame, ref: TableRef, out: pd.DataFrame, root: Path) -> dict[str, ElementPattern]:
    names = str_column(df, ref, "element", default=DEFAULT_ELEMENT)
    names = np.where(np.char.lower(names.astype(str)) == DEFAULT_ELEMENT, DEFAULT_ELEMENT, names).astype(object)
    elements: dict[str, ElementPattern] = {DEFAULT_ELEMENT: TR38901Element()}
    for name in pd.unique(names):
        if name in elements:
            continue
        first = int(np.flatnonzero(names == name)[0])
        path = root / name
        if path.is_dir():
            raise DataError(
                f"{ref.row(first)}: `element` = {name!r} is a folder ({path}); give a Planet/MSI pattern file."
            )
        if not path.is_file():
            raise DataError(
                f"{ref.row(first)}: `element` = {name!r}: file not found ({path}); give a Planet/MSI pattern file "
                f"relative to the scenario folder, `{DEFAULT_ELEMENT}`, or leave it empty."
            )
        try:
            elements[name] = read_msi(path)
        except DataError as exc:
            raise DataError(f"{ref.row(first)}: `element` = {name!r}: {exc}") from None
    out["element"] = pd.array(names, dtype="str")
    return elements


BAND_TOLERANCE = 0.10
"""A pattern measured at f₀ serves carriers within ±10 % of f₀ (docs/codebooks.md, the band rule)."""


def off_band(pattern_hz: float | None, carrier_hz: float) -> bool:
    """True when a pattern measured at ``pattern_hz`` may not serve ``carrier_hz`` (``None`` = any band)."""
    return pattern_hz is not None and abs(carrier_hz / pattern_hz - 1.0) > BAND_TOLERANCE


def _bands(ref: TableRef, out: pd.DataFrame, elements: dict[str, ElementPattern], meta: ScenarioMeta) -> None:
    """Refuse an element pattern or pattern codebook used off the band it was measured at."""
    for i, row in enumerate(out.itertuples(index=False)):
        element = elements[str(row.element)]
        pattern_hz = getattr(element, "frequency_hz", None)
        if pattern_hz is not None and off_band(pattern_hz, float(row.freq_hz)):
            raise DataError(
                f"{ref.row(i)}: cell {row.cell_id} on {fmt_number(row.freq_hz / 1e6)} MHz uses `element` = "
                f"{row.element!r} measured at {fmt_number(pattern_hz / 1e6)} MHz (beyond ±10 %); give the pattern "
                "of this band."
            )
        for column in ("ssb_codebook", "csi_codebook"):
            book = meta.codebooks[str(getattr(row, column))]
            if (
                isinstance(book, PatternCodebook)
                and book.frequency_hz
                and off_band(book.frequency_hz, float(row.freq_hz))
            ):
                raise DataError(
                    f"{ref.row(i)}: cell {row.cell_id} on {fmt_number(row.freq_hz / 1e6)} MHz uses `{column}` = "
                    f"{getattr(row, column)!r} (file {book.file!r}) measured at "
                    f"{fmt_number(book.frequency_hz / 1e6)} MHz (beyond ±10 %); give the patterns of this band."
                )


def _same_cells_as_round1(out: pd.DataFrame, ref: TableRef, round1: pd.DataFrame, round1_name: str) -> None:
    """Later rounds list the round-1 cells at the same positions, sites and carriers (``out`` in file order)."""
    ids1 = round1["cell_id"].to_numpy()  # sorted
    ids = out["cell_id"].to_numpy()
    problem = f"is not a cell of round 1 ({round1_name}); every round lists the same cells"
    raise_rows(ref, ~np.isin(ids, ids1), "cell_id", ids, problem)
    missing = np.setdiff1d(ids1, ids)
    if missing.size:
        raise DataError(
            f"{ref.name}: cell(s) {fmt_list(missing)} of round 1 ({round1_name}) are missing; every round lists "
            "the same cells (copy the unchanged ones from round 1)."
        )
    pos = np.searchsorted(ids1, ids)
    for column in ("site_id", *XYZ, "freq_hz"):
        before = round1[column].to_numpy()[pos]
        now = out[column].to_numpy()
        changed = np.abs(now - before) > (1e-3 if column in XYZ else 0)
        if changed.any():
            first = int(np.flatnonzero(changed)[0])
            problem = (
                f"differs from round 1 ({round1_name}: {fmt_value(before[first])}) for cell {ids[first]}; a new round "
                "changes only the antenna configuration (codebooks, azimuth, tilts), not the site, position "
                "or carrier"
            )
            raise_rows(ref, changed, column, out[column], problem)
