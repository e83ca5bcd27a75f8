"""Reading and writing tables: CSV or Parquet, chosen by the file extension.

Floats are written with the shortest repr that round-trips and pandas ≥ 3.1
parses them exactly (its one float converter), so a table written by
:func:`write_table` reads back bit for bit from CSV as from Parquet (tested).
Empty CSV fields read as NaN (missing).
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from rflscm.errors import DataError

TABLE_SUFFIXES = (".csv", ".parquet", ".pq")


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


def read_table(path: str | Path) -> pd.DataFrame:
    """Read a CSV or Parquet table (by extension).

    Raises:
        DataError: the file is missing, empty or not a readable table of its format.
    """
    path = Path(path)
    kind = table_kind(path)
    if not path.is_file():
        raise DataError(f"{path}: file not found.")
    try:
        if kind == "csv":
            return pd.read_csv(path, skipinitialspace=True)
        return pd.read_parquet(path)
    except pd.errors.EmptyDataError:
        raise DataError(f"{path.name} is empty (no header, no rows); it needs a header line and data rows.") from None
    except (pd.errors.ParserError, UnicodeDecodeError) as exc:
        raise DataError(f"{path.name}: not a readable CSV file ({_first_line(exc)}); save it as UTF-8 CSV.") from None
    except (OSError, ValueError) as exc:  # pyarrow.ArrowInvalid is a ValueError
        raise DataError(f"{path.name}: not a readable {kind} file ({_first_line(exc)}).") from None


def write_table(df: pd.DataFrame, path: str | Path) -> None:
    """Write ``df`` (without its index) as CSV or Parquet, by extension; NaN is an empty CSV field."""
    path = Path(path)
    kind = table_kind(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if kind == "csv":
        df.to_csv(path, index=False)
    else:
        df.to_parquet(path, index=False)


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__
