"""Column checks shared by every scenario table, vectorised and with spreadsheet-style errors.

Every check works on whole columns (pandas / numpy masks) and, when a row is
wrong, raises one :class:`DataError` line that names the file, the first bad
row, the column, the value received, what is allowed and how to fix it, plus
how many further rows have the same problem.  Rows are numbered as a
spreadsheet user sees them: ``row 1`` is the first *data* row; for CSV files
the text-editor line (header = line 1) is added, e.g. ``row 3 (line 4)``.
Checks run on the table in file order, before any sorting, so the numbers
match the file.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from rflscm.errors import DataError


@dataclass(frozen=True)
class TableRef:
    """Where a table came from, for error messages.

    ``name`` is the file as the user wrote it (e.g. ``measurements.parquet``);
    ``csv`` adds text-editor line numbers to row numbers.
    """

    name: str
    csv: bool = False
    lines: np.ndarray | None = field(default=None, compare=False)
    """int64 ``[num_rows]`` text-editor line of each CSV row when it is not ``row + 1`` (blank lines)."""

    def label(self, pos: int) -> str:
        """``"row N"`` (plus ``"(line L)"`` for CSV) for 0-based position ``pos`` in file order."""
        if not self.csv:
            return f"row {pos + 1}"
        line = int(self.lines[pos]) if self.lines is not None and pos < len(self.lines) else pos + 2
        return f"row {pos + 1} (line {line})"

    def row(self, pos: int) -> str:
        """``"<name> row N"`` for 0-based position ``pos`` in file order."""
        return f"{self.name} {self.label(pos)}"


def fmt_value(value: object) -> str:
    """A received value as it should appear in a message (floats keep their decimal point, text is quoted)."""
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return str(int(value))
    if value is None or (isinstance(value, float) and np.isnan(value)):
        return "empty"
    return repr(str(value))


def fmt_number(value: float) -> str:
    """Compact engineering form: 3.5e9, 2.1e9, 15, −120.5."""
    text = f"{value:.6g}"
    return text.replace("e+0", "e").replace("e+", "e").replace("e-0", "e-")


def fmt_list(items: Any, limit: int = 10) -> str:
    """``a, b, c`` (at most ``limit`` items, then ``… (N in all)``)."""
    items = list(items)
    shown = ", ".join(str(i) for i in items[:limit])
    return shown if len(items) <= limit else f"{shown}, … ({len(items)} in all)"


def raise_rows(ref: TableRef, mask: np.ndarray, column: str, values: Any, problem: str) -> None:
    """Raise a :class:`DataError` for the first row where ``mask`` is True (no-op when none is).

    Args:
        ref: the table, for the message.
        mask: bool ``[num_rows]`` in file order; True marks a bad row.
        column: the column named in the message.
        values: ``[num_rows]`` values shown in the message (the raw ones the user wrote).
        problem: what is wrong and how to fix it, e.g. ``"must lie in −90…90° (positive = down)"``.
    """
    mask = np.asarray(mask, dtype=bool)
    if not mask.any():
        return
    bad = np.flatnonzero(mask)
    first = int(bad[0])
    value = values.iloc[first] if isinstance(values, pd.Series) else np.asarray(values, dtype=object)[first]
    shown = "" if _is_missing(value) else f" = {fmt_value(value)}"
    message = f"{ref.row(first)}: `{column}`{shown} {problem}"
    if not message.endswith((".", "?")):
        message += "."
    if len(bad) > 1:
        message += f" {len(bad) - 1} more row(s) have the same problem."
    raise DataError(message)


def _is_missing(value: object) -> bool:
    try:
        return bool(pd.isna(value))
    except (TypeError, ValueError):
        return False


def check_not_empty(df: pd.DataFrame, ref: TableRef, what: str) -> None:
    """A table without data rows is an error (``what`` says what one row is, e.g. "one row per cell")."""
    if len(df) == 0:
        raise DataError(f"{ref.name} has no data rows; it needs {what}.")


def clean_column_names(df: pd.DataFrame, ref: TableRef) -> pd.DataFrame:
    """Strip blanks around header names; duplicate names are an error."""
    names = [str(c).strip().lstrip("\ufeff") for c in df.columns]  # blanks, and a UTF-8 BOM from spreadsheets
    seen: set[str] = set()
    for name in names:
        if name in seen:
            raise DataError(f"{ref.name}: column `{name}` appears twice in the header; keep one.")
        seen.add(name)
    df = df.copy(deep=False)
    df.columns = names
    return df


def require_columns(df: pd.DataFrame, ref: TableRef, required: list[str], required_text: str | None = None) -> None:
    """Every column of ``required`` must be present; the message lists them, what was found and close matches."""
    missing = [c for c in required if c not in df.columns]
    if not missing:
        return
    hints = []
    for name in missing:
        close = difflib.get_close_matches(name, [str(c) for c in df.columns], n=1, cutoff=0.6)
        if close:
            hints.append(f"`{close[0]}` → `{name}`?")
    hint = f" Rename {', '.join(hints)}" if hints else ""
    for separator, label in ((";", "';'"), ("\t", "tab"), ("|", "'|'")):
        if len(df.columns) == 1 and separator in str(df.columns[0]):
            hint = f" The header looks {label}-separated; save the file as comma-separated CSV."
    found = ", ".join(f"`{c}`" for c in df.columns) or "none"
    raise DataError(
        f"{ref.name}: missing column(s) {', '.join(f'`{c}`' for c in missing)}; "
        f"required: {required_text or ', '.join(required)}; found: {found}.{hint}"
    )


def _as_float(series: pd.Series, ref: TableRef, column: str) -> np.ndarray:
    """Float64 values ``[num_rows]`` of a column; text that is not a number is an error (all such rows counted)."""
    kind = series.dtype.kind if isinstance(series.dtype, np.dtype) else ""
    if pd.api.types.is_bool_dtype(series.dtype):
        raise_rows(ref, np.ones(len(series), bool), column, series, "is true/false; a number is needed")
    if kind and kind in "mMcV":  # dates, durations, complex numbers, raw bytes: not plain numbers
        problem = f"has type {series.dtype}; a plain number is needed"
        raise_rows(ref, np.ones(len(series), bool), column, series, problem)
    if pd.api.types.is_numeric_dtype(series.dtype):
        return series.to_numpy(dtype=np.float64, na_value=np.nan)
    if series.dtype == object:  # Python objects (lists, bytes, …) from Parquet: their text form is judged
        series = series.map(lambda v: v if v is None or isinstance(v, (str, int, float, np.number)) else repr(v))
    coerced = pd.to_numeric(series, errors="coerce")
    text = series.astype("string").str.strip()
    bad = (coerced.isna() & text.notna() & (text != "")).to_numpy(dtype=bool, na_value=False)
    problem = (
        "is not a number; write plain numbers (a dot as decimal separator, no units) and leave the field empty "
        "where there is no value (not N/A, null or NaN)"
    )
    raise_rows(ref, bad, column, series, problem)
    return coerced.to_numpy(dtype=np.float64, na_value=np.nan)


def float_column(
    df: pd.DataFrame,
    ref: TableRef,
    column: str,
    *,
    default: float | np.ndarray | None = None,
    allow_nan: bool = False,
    copy: bool = True,
) -> np.ndarray:
    """A numeric column as float64 ``[num_rows]``.

    A missing column or an empty value takes ``default`` (scalar or per row) when
    one is given; otherwise an empty value is an error unless ``allow_nan``.
    ±inf is always an error.  ``copy=False`` (no ``default``): the column's own float64 values where it has them,
    possibly a read-only view (a large table is not duplicated).
    """
    if column not in df.columns:
        if default is None:
            raise DataError(f"{ref.name}: missing column `{column}`.")
        return np.broadcast_to(np.asarray(default, dtype=np.float64), (len(df),)).copy()
    values = _as_float(df[column], ref, column)
    if copy or default is not None:
        values = np.array(values)  # writable copy: pandas may hand out read-only views
    nan = np.isnan(values)
    if default is not None and nan.any():
        values[nan] = np.broadcast_to(np.asarray(default, dtype=np.float64), values.shape)[nan]
    elif not allow_nan:
        raise_rows(ref, nan, column, df[column], "is empty (NaN); every row needs a value")
    raise_rows(ref, np.isinf(values), column, df[column], "is infinite; give a finite number")
    return values


MAX_INT = 2**53
"""Largest integer (ids, counts) a table may hold: every integer up to it is exact as a float64."""


def int_column(df: pd.DataFrame, ref: TableRef, column: str, *, default: int | None = None) -> np.ndarray:
    """An integer column as int64 ``[num_rows]`` (``3.0`` is accepted, ``3.5``, empty values and integers
    beyond ±2^53 are not)."""
    series = df[column] if column in df.columns else None
    if series is not None and isinstance(series.dtype, np.dtype) and series.dtype.kind == "i":
        values = series.to_numpy(dtype=np.int64)
        raise_rows(ref, _beyond(values, MAX_INT), column, series, _TOO_BIG)
        return values
    values = float_column(df, ref, column, default=None if default is None else float(default))
    fractional = values != np.round(values)
    raw = df[column] if column in df.columns else values
    raise_rows(ref, fractional, column, raw, "is not a whole number; give an integer")
    raise_rows(ref, _beyond(values, MAX_INT), column, raw, _TOO_BIG)
    return values.astype(np.int64)


def _beyond(values: np.ndarray, limit: float) -> np.ndarray:
    """``|values| > limit`` without a temporary of the values' size (a bool mask only)."""
    mask = values > limit
    mask |= values < -limit
    return mask


_TOO_BIG = f"is too large; integers here must lie within ±{MAX_INT} (2^53)"


def str_column(df: pd.DataFrame, ref: TableRef, column: str, *, default: str | None = None) -> np.ndarray:
    """A text column as an object array of stripped ``str`` ``[num_rows]``; empty values take ``default``.

    Numbers are accepted and turned into text (``8`` → ``"8"``, ``8.0`` → ``"8"``).
    """
    if column not in df.columns:
        if default is None:
            raise DataError(f"{ref.name}: missing column `{column}`.")
        return np.full(len(df), default, dtype=object)
    series = df[column]
    if series.dtype == object:  # unhashable objects (lists from Parquet) are judged by their text
        series = series.map(lambda v: v if v is None or isinstance(v, (str, int, float, np.number)) else repr(v))
    codes, uniques = pd.factorize(series, use_na_sentinel=True)
    texts = np.array([_text_of(u) for u in uniques] + [""], dtype=object)  # code −1 → ""
    values = texts[codes]
    empty = values == ""
    if default is not None:
        values[empty] = default
    else:
        raise_rows(ref, empty, column, df[column], "is empty; every row needs a value")
    return values


def _text_of(value: object) -> str:
    if isinstance(value, (float, np.floating)) and float(value).is_integer():
        return str(int(value))
    return str(value).strip()


def duplicate_rows(
    ref: TableRef, df: pd.DataFrame, keys: list[str], fix: str, packed: np.ndarray | None = None
) -> None:
    """Raise if two rows share the values of ``keys`` (named with both rows' numbers).

    ``packed`` (int64 ``[num_rows]``), when given, is one integer per row that is equal exactly
    when the ``keys`` are: hashing one integer column is much faster than several columns.
    """
    if packed is not None:  # a stable sort: pandas 3's hash of 12 M integers took 68 s, numpy's sort 1.3 s
        order = np.argsort(packed, kind="stable")
        ranked = packed[order]
        repeats = order[1:][ranked[1:] == ranked[:-1]]  # every row but the first of its key, as keep="first"
        dup = np.zeros(len(packed), dtype=bool)
        dup[repeats] = True
    else:
        dup = df[keys].duplicated(keep="first").to_numpy()
    if not dup.any():
        return
    later = int(np.flatnonzero(dup)[0])
    if packed is not None:
        same = packed == packed[later]
    else:
        same = np.ones(len(df), dtype=bool)
        for key in keys:
            same &= (df[key] == df[key].iloc[later]).to_numpy()
    first = int(np.flatnonzero(same)[0])
    shown = ", ".join(fmt_value(df[k].iloc[later]) for k in keys)
    label = f"`{keys[0]}`" if len(keys) == 1 else "(" + ", ".join(f"`{k}`" for k in keys) + ")"
    shown = shown if len(keys) == 1 else f"({shown})"
    raise DataError(
        f"{ref.row(later)}: {label} = {shown} duplicates {ref.label(first)}; "
        f"{fix}. {int(dup.sum())} duplicate row(s) in all."
    )


def check_unknown_columns(df: pd.DataFrame, ref: TableRef, known: list[str] | tuple[str, ...]) -> list[str]:
    """Columns of ``df`` that rflscm does not use (returned, for ``check`` to list as ignored).

    A column that is not known but looks like a known column that is absent (same name in another case,
    or a close spelling) is an error with a did-you-mean: otherwise the known column would silently take
    its default.
    """
    present = {str(c) for c in df.columns}
    absent = [k for k in known if k not in present]
    unknown = [str(c) for c in df.columns if str(c) not in known]
    for name in unknown:
        same_case = [k for k in absent if k.lower() == name.lower().replace(" ", "_")]
        close = same_case or difflib.get_close_matches(name, absent, n=1, cutoff=0.8)
        if close:
            raise DataError(
                f"{ref.name}: column `{name}` is not a column rflscm knows; did you mean `{close[0]}`? Rename it "
                f"(as written, it would be ignored and `{close[0]}` would take its default)."
            )
    return unknown
