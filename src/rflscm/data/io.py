"""Reading and writing tables: CSV or Parquet, chosen by the file extension.

Floats are written with the shortest repr that round-trips and pandas ≥ 3.1
parses them exactly (its one float converter), so a table written by
:func:`write_table` reads back bit for bit from CSV as from Parquet (tested).

Reading is strict, so that no row or value changes without a word (issue 14):

* only an empty CSV field is missing (NaN); text such as ``N/A``, ``null`` or
  ``None`` stays text, and the column checks report it as "not a number";
* every CSV row must have as many fields as the header (a short row or a file
  cut off in the middle of a row is an error naming the line);
* a header naming a column twice is an error (pandas would rename it ``x.1``);
* bytes that are not UTF-8, NUL bytes, folders, unreadable files and damaged
  Parquet files are one-line :class:`DataError` messages naming the file.

Blank lines are skipped; when there are any, the text-editor line number of
every data row is kept in ``df.attrs["line_numbers"]`` so messages still point
at the right line.
"""

from __future__ import annotations

import csv
import io
from pathlib import Path

import numpy as np
import pandas as pd

from rflscm.config import read_file_bytes
from rflscm.data.safe_io import atomic_write
from rflscm.errors import DataError

TABLE_SUFFIXES = (".csv", ".parquet", ".pq")
LINE_NUMBERS = "line_numbers"
"""``df.attrs`` key: int64 ``[num_rows]`` text-editor line of each CSV data row (only when not row + 2)."""


def table_kind(path: str | Path) -> str:
    """``"csv"`` or ``"parquet"`` from the extension; anything else is a :class:`DataError`."""
    suffix = Path(path).suffix.lower()
    if suffix == ".csv":
        return "csv"
    if suffix in (".parquet", ".pq"):
        return "parquet"
    raise DataError(
        f"{Path(path).name}: unsupported table format {suffix or '(no extension)'!r}; use .csv or .parquet."
    )


def read_bytes(path: str | Path, what: str = "file") -> bytes:
    """The bytes of ``path``; a missing file, a folder or an unreadable file is a :class:`DataError`."""
    return read_file_bytes(path, what, DataError)


def decode_text(data: bytes, name: str) -> str:
    """UTF-8 text of ``data`` (a UTF-8 BOM is dropped); other encodings are an error naming the line."""
    if data.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise DataError(f"{name}: the file is UTF-16 encoded; save it as UTF-8.")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        where = f"line {line} (the header)" if line == 1 else f"row {line - 1} (line {line})"
        raise DataError(
            f"{name} {where}: byte 0x{data[exc.start]:02x} is not UTF-8 text; save the file as UTF-8 "
            "(in a spreadsheet: CSV UTF-8)."
        ) from None
    if "\x00" in text:
        line = text[: text.index("\x00")].count("\n") + 1
        raise DataError(f"{name} line {line}: a NUL byte; this is not a text file (save the table as UTF-8 CSV).")
    return text


def read_table(path: str | Path, where: dict[str, object] | None = None) -> pd.DataFrame:
    """Read a CSV or Parquet table (by extension); ``where`` (column → value) keeps only the rows equal to every
    value (a Parquet file is filtered as it is read, so the rows left out never take memory).

    Raises:
        DataError: the file is missing, a folder, unreadable, empty, not a readable table of its format,
            has a short or long row, or names a column twice.
    """
    path = Path(path)
    kind = table_kind(path)
    data = read_bytes(path, "table file")
    if kind == "csv":
        df = _read_csv(data, path.name)
        if where:
            keep = np.ones(len(df), dtype=bool)
            for column, value in where.items():
                keep &= (df[column] == value).to_numpy()
            df = df[keep].reset_index(drop=True)
        return df
    try:
        # Page checksums verified (a flipped value in a file that has them is an error, not data); one thread:
        # a threaded read of a corrupted page can abort the process (exit 134) instead of raising.
        # Arrow's buffers are released column by column as pandas takes them (self_destruct, split_blocks): the
        # read's peak is about the table's size once, not twice (issue 29, memory).
        df = pd.read_parquet(
            io.BytesIO(data),
            page_checksum_verification=True,
            use_threads=False,
            filters=[(column, "==", value) for column, value in where.items()] if where else None,
            to_pandas_kwargs={"self_destruct": True, "split_blocks": True},
        )
    except Exception as exc:
        raise DataError(f"{path.name}: not a readable Parquet file ({_first_line(exc)}).") from None
    names = [str(c) for c in df.columns]
    duplicated = sorted({n for n in names if names.count(n) > 1})
    if duplicated:
        raise DataError(f"{path.name}: column `{duplicated[0]}` appears twice in the header; keep one.")
    return df


def _read_csv(data: bytes, name: str) -> pd.DataFrame:
    text = decode_text(data, name)
    records = _records(text, name)  # [(line number, number of fields)] of every non-blank record
    if not records:
        raise DataError(f"{name} is empty (no header, no rows); it needs a header line and data rows.")
    header = next(csv.reader([text.splitlines()[records[0][0] - 1]], skipinitialspace=True))
    names = [h.strip().lstrip("\ufeff") for h in header]
    duplicated = [n for i, n in enumerate(names) if n and n in names[:i]]
    if duplicated:
        raise DataError(
            f"{name} line {records[0][0]}: column `{duplicated[0]}` appears twice in the header; keep one "
            "(or rename the other)."
        )
    lines = np.array([r[0] for r in records[1:]], dtype=np.int64)
    counts = np.array([r[1] for r in records[1:]], dtype=np.int64)
    _check_field_counts(text, name, len(names), lines, counts)
    try:
        df = pd.read_csv(io.StringIO(text), skipinitialspace=True, keep_default_na=False, na_values=[""])
    except (pd.errors.ParserError, ValueError, csv.Error) as exc:
        raise DataError(f"{name}: not a readable CSV file ({_first_line(exc)}).") from None
    if len(df) != len(lines):  # never change the number of rows without a word
        raise DataError(
            f"{name}: {len(lines)} data rows in the file but {len(df)} could be read; check quoting and line breaks."
        )
    if len(lines) and not np.array_equal(lines, np.arange(len(lines)) + 2):
        df.attrs[LINE_NUMBERS] = lines
    return df


def _records(text: str, name: str) -> list[tuple[int, int]]:
    """``(line, fields)`` of every non-blank CSV record (a quoted field may span lines)."""
    out: list[tuple[int, int]] = []
    if '"' not in text:  # fast path: one record per line
        for i, line in enumerate(text.splitlines(), start=1):
            if line.strip():
                out.append((i, line.count(",") + 1))
        return out
    reader = csv.reader(io.StringIO(text), skipinitialspace=True, strict=True)
    start = 1
    try:
        for row in reader:
            if any(field.strip() for field in row) or len(row) > 1:
                out.append((start, len(row)))
            start = reader.line_num + 1
    except csv.Error as exc:
        raise DataError(
            f'{name} line {reader.line_num}: {exc}; a quote (") is not closed or is misplaced (a truncated file?).'
        ) from None
    return out


def _check_field_counts(text: str, name: str, num_columns: int, lines: np.ndarray, counts: np.ndarray) -> None:
    bad = np.flatnonzero(counts != num_columns)
    if not bad.size:
        return
    first = int(bad[0])
    line, found = int(lines[first]), int(counts[first])
    more = f" {bad.size - 1} more row(s) have a wrong number of fields." if bad.size > 1 else ""
    if found < num_columns:
        last = first == len(lines) - 1 and not text.endswith(("\n", "\r"))
        why = "the file ends in the middle of this row (was it cut off?)" if last else "the row is cut short"
        fix = "complete the row (an empty field between commas means 'not reported')"
    else:
        why = "an extra comma, or a decimal comma (write 12.5, not 12,5)?"
        fix = "quote text that contains commas"
    raise DataError(f"{name} line {line}: {found} field(s) where the header has {num_columns}; {why} — {fix}.{more}")


def write_table(df: pd.DataFrame, path: str | Path) -> None:
    """Write ``df`` (without its index) as CSV or Parquet (with page checksums), by extension; NaN is an empty CSV
    field.  Atomic (:func:`rflscm.data.safe_io.atomic_write`): a failure leaves the previous file as it was."""
    path = Path(path)
    kind = table_kind(path)
    if path.is_dir():
        raise DataError(f"{path}: is a folder; give a file name to write the table to.")

    def write(tmp: Path) -> None:
        if kind == "csv":
            df.to_csv(tmp, index=False)
        else:
            df.to_parquet(tmp, index=False, write_page_checksum=True)

    atomic_write(path, write, "table")  # a unique temporary file, renamed when complete: never a fragment


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__
