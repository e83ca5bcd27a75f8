"""The measurements table's validation does not multiply the table (issue 29, memory)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from rflscm.data import Scenario, load_scenario, read_table, save_scenario
from rflscm.data.columns import TableRef
from rflscm.data.measurements import _has_duplicates, _packed_key, normalise_measurements
from rflscm.errors import DataError


def test_a_clean_parquet_table_is_kept_not_copied(tiny: Scenario, tmp_path: Path) -> None:
    root = save_scenario(tiny, tmp_path / "pq", table_format="parquet")
    raw = read_table(root / "measurements.parquet")
    s = load_scenario(root)
    out = normalise_measurements(raw, TableRef("m"), s.meta, s.cells, s.grid_ids(), s.meta.grids)
    assert out.equals(s.measurements) and out.equals(tiny.measurements)
    for column in ("round", "cell_id", "grid_id", "beam_id", "rsrp_dbm"):
        assert np.shares_memory(out[column].to_numpy(), raw[column].to_numpy()), column


def test_messy_beam_types_are_normalised_to_the_same_table(tiny: Scenario) -> None:
    messy = tiny.measurements.copy()
    messy["beam_type"] = np.where(messy["beam_type"] == "ssb", " SSB", "Csi ")
    again = tiny.with_measurements(messy)
    assert again.measurements.equals(tiny.measurements)
    assert again.measurements["beam_type"].dtype == tiny.measurements["beam_type"].dtype


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_packed_key_and_sorted_duplicate_check_agree_with_pandas(seed: int) -> None:
    rng = np.random.default_rng(seed)
    shape = (2, 50, 300, 2, 32)
    positions = tuple(
        rng.integers(0, n, 5000).astype(dt)
        for n, dt in zip(shape, [np.int8, np.int16, np.int32, np.int8, np.int64], strict=True)
    )
    key = _packed_key(positions, shape)
    assert np.array_equal(key, np.ravel_multi_index(tuple(p.astype(np.int64) for p in positions), shape))
    assert _has_duplicates(key) == bool(pd.Series(key).duplicated().any())
    unique = np.unique(key)
    assert not _has_duplicates(unique) and _has_duplicates(np.concatenate([unique, unique[-1:]]))


def test_a_duplicate_is_still_named_with_both_rows(tiny: Scenario) -> None:
    m = tiny.measurements
    doubled = pd.concat([m, m.iloc[[3]]], ignore_index=True)
    with pytest.raises(DataError, match=rf"row {len(m) + 1}: .* duplicates row 4; .*1 duplicate row\(s\) in all"):
        tiny.with_measurements(doubled)


def test_check_summary_counts_match_a_group_by_of_the_table(tiny: Scenario) -> None:
    from rflscm.data.reporting import reported_fraction
    from rflscm.data.summary import measurement_stats

    m = tiny.measurements
    stats = measurement_stats(tiny).set_index(["round", "beam_type"])
    for (rnd, bt), rows in m.groupby(["round", "beam_type"]):
        row = stats.loc[(rnd, bt)]
        assert row["rows"] == len(rows)
        assert row["pairs"] == len(rows[["cell_id", "grid_id"]].drop_duplicates())
        assert row["cells"] == rows["cell_id"].nunique() and row["grids"] == rows["grid_id"].nunique()
        assert row["missing"] == rows["rsrp_dbm"].isna().mean()
        assert row["below_threshold"] == int((rows["rsrp_dbm"] < tiny.meta.rsrp_threshold_dbm).sum())
    frac = reported_fraction(tiny).set_index(["round", "beam_type"])
    for rnd in sorted(m["round"].unique()):
        sub = m[m["round"] == rnd]
        pairs = sub[["cell_id", "grid_id"]].drop_duplicates()
        for bt in ("ssb", "csi"):
            possible = sum(tiny.num_beams(int(c), bt, int(rnd)) for c in pairs["cell_id"])
            reported = int(sub[sub["beam_type"] == bt]["rsrp_dbm"].notna().sum())
            assert frac.loc[(rnd, bt), "possible"] == possible and frac.loc[(rnd, bt), "reported"] == reported


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_select_rows_equals_a_boolean_mask_and_shares_a_contiguous_run(seed: int) -> None:
    from rflscm.data.measurements import select_rows

    rng = np.random.default_rng(seed)
    table = pd.DataFrame({"round": np.repeat([1, 2], 50), "v": rng.normal(size=100), "k": np.arange(100)})
    run = (table["round"] == 1).to_numpy()
    scattered = rng.random(100) < 0.4
    for mask in (run, scattered, np.zeros(100, bool), np.ones(100, bool)):
        got = select_rows(table, mask)
        assert got.equals(table[mask].reset_index(drop=True))
    shared = select_rows(table, run)
    assert np.shares_memory(shared["v"].to_numpy(), table["v"].to_numpy())  # one run: a slice, not a copy
    assert not np.shares_memory(select_rows(table, scattered)["v"].to_numpy(), table["v"].to_numpy())
    shared.loc[0, "v"] = 1e9  # copy-on-write: writing the slice leaves the table as it was
    assert table["v"].iloc[0] != 1e9


def test_reported_pairs_are_the_distinct_sorted_pairs_with_a_reported_beam(tiny: Scenario) -> None:
    from rflscm.data.measurements import reported_pairs

    m = tiny.measurements
    for rnd in (1, 2):
        rows = m[(m["round"] == rnd) & m["rsrp_dbm"].notna()]
        expect = rows[["cell_id", "grid_id"]].drop_duplicates().sort_values(["cell_id", "grid_id"], ignore_index=True)
        got = reported_pairs(m, rnd)
        assert got.equals(expect) and len(got) > 0
    silent = m.assign(rsrp_dbm=np.nan)
    assert reported_pairs(silent).empty
