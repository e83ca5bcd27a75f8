"""Tiles of a network (issue 29): every cell in exactly one tile, compact and deterministic."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from rflscm.data.parts import plan_tiles
from rflscm.errors import ConfigError, DataError


def network(num_sites: int, silent: tuple[int, ...] = (), seed: int = 0) -> SimpleNamespace:
    """A duck-typed scenario: ``num_sites`` sites of 3 cells on a random plan, round-1 reports at a few grids
    near each site (none for the ``silent`` sites' cells)."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(0.0, 1000.0, size=(num_sites, 2))
    cells = pd.DataFrame(
        {
            "cell_id": np.arange(3 * num_sites) + 100,
            "site_id": np.repeat(np.arange(num_sites) + 1, 3),
            "x": np.repeat(xy[:, 0], 3),
            "y": np.repeat(xy[:, 1], 3),
        }
    )
    rows = []
    for cell, site in zip(cells["cell_id"], cells["site_id"], strict=True):
        for grid in rng.choice(50, size=5, replace=False) + 10 * site:
            value = np.nan if site in silent else -90.0
            rows.append((1, cell, grid, value))
            rows.append((2, cell, grid + 1000, -80.0))  # round 2: not what tiles are cut by
    m = pd.DataFrame(rows, columns=["round", "cell_id", "grid_id", "rsrp_dbm"])
    return SimpleNamespace(cells={1: cells}, measurements=m, meta=SimpleNamespace(name="net"))


def test_every_cell_is_in_exactly_one_tile_and_the_tiles_are_balanced() -> None:
    net = network(10)
    tiles = plan_tiles(net, 3)
    assert len(tiles) == 4 and [t.index for t in tiles] == [0, 1, 2, 3]
    cells = np.concatenate([t.cells for t in tiles])
    assert sorted(cells.tolist()) == sorted(net.cells[1]["cell_id"].tolist())  # each exactly once
    sizes = [len(t.sites) for t in tiles]
    assert sum(sizes) == 10 and max(sizes) - min(sizes) <= 1
    m = net.measurements
    for t in tiles:  # a tile's cells are its sites' cells, its grids where they reported round 1
        own = net.cells[1][net.cells[1]["site_id"].isin(t.sites)]["cell_id"]
        assert sorted(t.cells) == sorted(own.tolist())
        heard = m[(m["round"] == 1) & m["cell_id"].isin(t.cells) & m["rsrp_dbm"].notna()]["grid_id"]
        assert list(t.grids) == sorted(set(heard.tolist()))


def test_the_plan_is_deterministic_and_does_not_depend_on_the_row_order() -> None:
    net = network(9, seed=3)
    shuffled = SimpleNamespace(
        cells={1: net.cells[1].sample(frac=1.0, random_state=1)},
        measurements=net.measurements.sample(frac=1.0, random_state=2),
        meta=net.meta,
    )
    assert plan_tiles(net, 2) == plan_tiles(net, 2) == plan_tiles(shuffled, 2)


def test_tiles_are_spatially_compact() -> None:
    # two far-apart clusters of three sites: tiles of three sites are the clusters
    net = network(6)
    net.cells[1].loc[net.cells[1]["site_id"] <= 3, "x"] += 10_000.0
    assert sorted(t.sites for t in plan_tiles(net, 3)) == [(1, 2, 3), (4, 5, 6)]


def test_one_tile_per_site_and_one_tile_for_everything() -> None:
    net = network(5)
    assert [len(t.sites) for t in plan_tiles(net, 1)] == [1] * 5
    (whole,) = plan_tiles(net, 5)
    assert whole.sites == (1, 2, 3, 4, 5) and len(whole.cells) == 15
    assert len(plan_tiles(net, 100)) == 1


def test_a_tile_without_round_1_reports_joins_the_nearest_tile() -> None:
    net = network(4, silent=(2,))
    cells = net.cells[1]
    cells.loc[cells["site_id"] == 2, ["x", "y"]] = cells.loc[cells["site_id"] == 3, ["x", "y"]].to_numpy() + 1.0
    tiles = plan_tiles(net, 1)
    assert len(tiles) == 3
    (joined,) = [t for t in tiles if 2 in t.sites]
    assert joined.sites == (2, 3) and len(joined.cells) == 6  # site 2's cells are still owned by a tile


def test_nothing_to_tile_and_a_tile_of_no_site_are_refused() -> None:
    with pytest.raises(ConfigError, match="at least one site"):
        plan_tiles(network(3), 0)
    with pytest.raises(DataError, match="no reported round-1 RSRP"):
        plan_tiles(network(2, silent=(1, 2)), 1)


def test_tiles_are_cut_by_training_pairs_not_by_sites() -> None:
    # a dense cluster (three sites, 20x the pairs of each other site) in a network of nine: cut by sites, one tile
    # would hold the cluster and most of the pairs; cut by pairs, the cluster's tiles hold fewer sites
    net = network(9, seed=4)
    m, cells = net.measurements, net.cells[1]
    dense = cells[cells["site_id"] <= 3]["cell_id"]
    extra = []
    for cell in dense:
        extra += [(1, int(cell), 5000 + 10 * int(cell) + k, -85.0) for k in range(100)]
    net.measurements = pd.concat([m, pd.DataFrame(extra, columns=m.columns)], ignore_index=True)
    cells.loc[cells["site_id"] <= 3, ["x", "y"]] = cells.loc[cells["site_id"] <= 3, ["x", "y"]] * 0.01  # together
    tiles = plan_tiles(net, 3)
    assert len(tiles) == 3
    pairs = [t.pairs for t in tiles]
    reported = net.measurements
    reported = reported[(reported["round"] == 1) & reported["rsrp_dbm"].notna()]
    assert sum(pairs) == len(reported[["cell_id", "grid_id"]].drop_duplicates())
    for t in tiles:  # a tile's pairs are its cells' distinct reported pairs
        own = reported[reported["cell_id"].isin(t.cells)]
        assert t.pairs == len(own[["cell_id", "grid_id"]].drop_duplicates())
    by_sites = max(pairs) / min(pairs)
    assert by_sites < 4.0, pairs  # 3 dense sites hold ~87 % of the pairs: cut by sites the ratio would be ~20
    assert min(len(t.sites) for t in tiles) == 1 and max(len(t.sites) for t in tiles) >= 5
