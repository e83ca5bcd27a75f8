"""PairLookup answers what pandas' MultiIndex.get_indexer would, on packed and unpackable ids alike."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rflscm.data.pair_lookup import PairLookup

IDS = st.one_of(st.integers(0, 40), st.integers(-(2**40), 2**40))


def _expected(table: pd.MultiIndex, cells: np.ndarray, grids: np.ndarray) -> np.ndarray:
    if not len(table):
        return np.full(len(cells), -1)
    first = ~table.duplicated()
    rows = np.flatnonzero(first)
    at = table[first].get_indexer(pd.MultiIndex.from_arrays([cells, grids]))
    return np.where(at >= 0, rows[np.maximum(at, 0)], -1)


@settings(max_examples=200, deadline=None)
@given(
    table=st.lists(st.tuples(st.integers(0, 40), st.integers(0, 40)), max_size=60),
    asked=st.lists(st.tuples(IDS, IDS), max_size=60),
    wide=st.booleans(),
)
def test_rows_match_pandas(table, asked, wide) -> None:
    if wide:  # an id beyond 31 bits: the pandas path
        table = [*table, (2**40, 3)]
    cells = np.array([c for c, _ in table], np.int64)
    grids = np.array([g for _, g in table], np.int64)
    q_cells = np.array([c for c, _ in asked] + [c for c, _ in table[:5]], np.int64)
    q_grids = np.array([g for _, g in asked] + [g for _, g in table[:5]], np.int64)
    got = PairLookup(cells, grids).rows(q_cells, q_grids)
    want = _expected(pd.MultiIndex.from_arrays([cells, grids]), q_cells, q_grids)
    np.testing.assert_array_equal(got, want)


def test_kept_lookup_follows_a_replaced_table() -> None:
    class Holder:
        pass

    holder = Holder()
    first = pd.MultiIndex.from_arrays([np.array([1, 2]), np.array([10, 20])])
    assert PairLookup.kept_by(holder, first) is PairLookup.kept_by(holder, first)
    second = pd.MultiIndex.from_arrays([np.array([2]), np.array([20])])
    assert PairLookup.kept_by(holder, second).rows(np.array([2, 1]), np.array([20, 10])).tolist() == [0, -1]


def test_mismatched_columns_are_refused() -> None:
    with pytest.raises(ValueError, match="differ in length"):
        PairLookup(np.arange(3), np.arange(2))
