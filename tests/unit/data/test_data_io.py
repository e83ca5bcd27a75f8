"""Tables: CSV / Parquet round trips and unreadable files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from rflscm.data import read_table, write_table
from rflscm.errors import DataError


def _table() -> pd.DataFrame:
    rng = np.random.default_rng(1)
    return pd.DataFrame(
        {
            "cell_id": np.array([3, 1, 2], dtype=np.int64),
            "value": rng.normal(size=3) * 1e9 + np.array([0.1, 1 / 3, np.pi]),  # needs all 17 digits
            "rsrp_dbm": [-80.0, np.nan, -101.5],
            "name": ["a", "b c", "ssb8"],
        }
    )


@pytest.mark.parametrize("suffix", [".csv", ".parquet"])
def test_round_trip_is_exact(tmp_path: Path, suffix: str) -> None:
    df = _table()
    write_table(df, tmp_path / f"t{suffix}")
    back = read_table(tmp_path / f"t{suffix}")
    assert list(back.columns) == list(df.columns)
    np.testing.assert_array_equal(back["cell_id"].to_numpy(), df["cell_id"].to_numpy())
    assert back["value"].to_numpy().tobytes() == df["value"].to_numpy().tobytes()  # bit-exact floats
    assert np.isnan(back["rsrp_dbm"][1]) and back["rsrp_dbm"][2] == -101.5
    assert back["name"].tolist() == ["a", "b c", "ssb8"]


def test_unsupported_extension(tmp_path: Path) -> None:
    (tmp_path / "t.xlsx").write_text("x")
    with pytest.raises(DataError, match=r"t\.xlsx: unsupported table format '\.xlsx'; use \.csv or \.parquet"):
        read_table(tmp_path / "t.xlsx")


def test_missing_and_broken_files(tmp_path: Path) -> None:
    with pytest.raises(DataError, match="file not found"):
        read_table(tmp_path / "none.csv")
    (tmp_path / "empty.csv").write_text("")
    with pytest.raises(DataError, match=r"empty\.csv is empty"):
        read_table(tmp_path / "empty.csv")
    (tmp_path / "broken.parquet").write_bytes(b"not parquet at all")
    with pytest.raises(DataError, match=r"broken\.parquet: not a readable Parquet file"):
        read_table(tmp_path / "broken.parquet")


def test_strict_csv_reading(tmp_path) -> None:
    """Issue 14: only an empty field is missing; quoted fields may span lines; line numbers survive blank lines."""
    path = tmp_path / "t.csv"
    path.write_text('a,b,c\n1,N/A,\n\n2,"x\ny",3\n')
    df = read_table(path)
    assert len(df) == 2 and df["b"].tolist() == ["N/A", "x\ny"] and df["c"].isna().tolist() == [True, False]
    assert df.attrs["line_numbers"].tolist() == [2, 4]
    path.write_text("a,b\n1,2\n3\n")
    with pytest.raises(DataError, match=r"t.csv line 3: 1 field\(s\) where the header has 2; the row is cut short"):
        read_table(path)
    path.write_text("a,b\n1,2\n3")
    with pytest.raises(DataError, match=r"t.csv line 3: 1 field\(s\) where the header has 2; the file ends in the"):
        read_table(path)
    path.write_text("a,a\n1,2\n")
    with pytest.raises(DataError, match="column `a` appears twice"):
        read_table(path)


@pytest.mark.parametrize("ext", [".parquet", ".csv"])
def test_read_table_keeps_only_the_rows_where_every_column_equals_its_value(tmp_path: Path, ext: str) -> None:
    table = pd.DataFrame(
        {"round": [1, 2, 2, 2], "beam_type": ["ssb", "ssb", "csi", "ssb"], "rsrp_dbm": [-80.0, -81.0, -82.0, -83.0]}
    )
    write_table(table, tmp_path / f"t{ext}")
    got = read_table(tmp_path / f"t{ext}", where={"round": 2, "beam_type": "ssb"})
    assert got["rsrp_dbm"].tolist() == [-81.0, -83.0]
    assert len(read_table(tmp_path / f"t{ext}")) == 4
