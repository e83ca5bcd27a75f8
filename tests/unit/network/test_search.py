"""Batched candidate sensing equals the scenario's sensing matrix; the search finds known optima."""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np
import pytest
import torch
from network_helpers import GRID, load, pencil_scenario, single_bin_cache

from rflscm.network.candidates import CellSensing
from rflscm.network.kpi import KPIConfig
from rflscm.network.optimize import replace_cells
from rflscm.network.search import (
    NetworkEvaluator,
    coordinate_descent,
    differential_evolution,
)
from rflscm.network.space import build_space, cells_table


@pytest.fixture
def scen(tmp_path: Path):
    return load(pencil_scenario(tmp_path / "pencil"))


NO_STEP = {"max_step": {"mech_tilt_deg": None, "elec_tilt_deg": None, "total_tilt_deg": None, "azimuth_deg": None}}


def test_candidate_matrices_equal_scenario_sensing(scen) -> None:
    space = build_space(NO_STEP, scen.cells[1], scen.meta.codebooks)
    dirs = GRID.directions(dtype=torch.float32)
    bins = torch.arange(0, GRID.num_bins, 7)
    pos = 1  # cell 12: ssb8, tilts 2/4
    sensing = CellSensing(scen, 12, 1, dirs[bins], space.cells[pos])
    opts = space.cells[pos]
    cands = [(0, 3, 5, 2), (1, 0, 0, 12), opts.current]
    got = sensing.matrices(cands)
    for k, index in enumerate(cands):
        config = [c.current for c in space.cells]
        config[pos] = index
        table = cells_table(scen.cells[1], space, config)
        ref = replace_cells(scen, 9, table).sensing(12, "ssb", GRID, round=9)[:, bins]  # [beams, bins]
        nb = ref.shape[0]
        torch.testing.assert_close(got[k, :nb], ref, rtol=2e-4, atol=1e-12)
        assert torch.all(got[k, nb:] == 0)


def _one_free_cell(scen, spec_cell: dict) -> tuple:
    spec = {"cells": {11: spec_cell}, "frozen": [12], **NO_STEP}
    return build_space(spec, scen.cells[1], scen.meta.codebooks)


def test_search_finds_the_obvious_tilt(scen) -> None:
    # one path 12° below the horizon, straight along cell 11's azimuth (60° from north = 30° CCW from east):
    # the pencil beam covers it best with 12° of mechanical down-tilt.
    space = _one_free_cell(
        scen,
        {
            "elec_tilt_deg": {"min": 0, "max": 0},
            "azimuth_offset_deg": {"min": 0, "max": 0},
            "ssb_codebooks": ["pencil"],
        },
    )
    cache = single_bin_cache(scen, -12.0, 30.0, 1e-15)
    ev = NetworkEvaluator(scen, 1, cache, space, KPIConfig(), "sinr")
    result = coordinate_descent(ev, restarts=1)
    chosen = space.cells[0].config(result.config[0])
    assert chosen["mech_tilt_deg"] == 12.0
    assert result.objective > result.base_objective
    assert ev.num_changed() == 1 and result.config[1] == space.cells[1].current  # cell 12 frozen


def _brute_force(ev: NetworkEvaluator, pos: int) -> tuple[float, tuple[int, ...]]:
    opts = ev.space.cells[pos]
    cands = [tuple(c) for c in itertools.product(*(range(n) for n in opts.sizes()))]
    scores = ev.score_cell(pos, cands)
    k = int(torch.argmax(scores))
    return float(scores[k]), cands[k]


def test_coordinate_descent_reaches_the_brute_force_optimum(scen) -> None:
    space = _one_free_cell(
        scen,
        {
            "mech_tilt_deg": {"min": 0, "max": 15, "step": 1},
            "elec_tilt_deg": {"min": 0, "max": 0},
            "azimuth_offset_deg": {"min": -30, "max": 30, "step": 5},
            "ssb_codebooks": ["pencil"],
        },
    )
    cache = single_bin_cache(scen, -8.0, 45.0, 1e-15)  # 15° off the present azimuth, 8° down
    ev = NetworkEvaluator(scen, 1, cache, space, KPIConfig(), "sinr")
    best, _ = _brute_force(ev, 0)
    result = coordinate_descent(ev, restarts=2)
    assert result.objective == pytest.approx(best, abs=1e-6)
    values = space.cells[0].config(result.config[0])
    assert values["mech_tilt_deg"] == 8.0 and values["azimuth_deg"] == 45.0  # 60° − 15°: 45° from north


def test_differential_evolution_improves_and_respects_the_space(scen) -> None:
    space = _one_free_cell(
        scen,
        {
            "elec_tilt_deg": {"min": 0, "max": 0},
            "azimuth_offset_deg": {"min": 0, "max": 0},
        },
    )
    cache = single_bin_cache(scen, -12.0, 30.0, 1e-15)
    ev = NetworkEvaluator(scen, 1, cache, space, KPIConfig(), "sinr")
    result = differential_evolution(ev, time_budget_s=2.0, seed=0)
    assert result.objective >= result.base_objective
    assert result.config[1] == space.cells[1].current
    assert np.isfinite(result.objective)


def test_max_changed_cells_is_respected(scen) -> None:
    spec = {"max_changed_cells": 1}
    space = build_space(spec, scen.cells[1], scen.meta.codebooks)
    cache = single_bin_cache(scen, -12.0, 30.0, 1e-15)
    ev = NetworkEvaluator(scen, 1, cache, space, KPIConfig(), "sinr")
    coordinate_descent(ev, restarts=2)
    assert ev.num_changed() <= 1


def test_cells_sharing_a_panel_never_get_different_azimuths(scen) -> None:
    cells = scen.cells[1].copy()
    cells["azimuth_deg"] = 60.0  # 3.5 and 2.1 GHz cells of one site on one panel
    scen = replace_cells(scen, 1, cells)
    space = build_space({"defaults": {"ssb_codebooks": ["pencil", "ssb8"]}}, cells, scen.meta.codebooks)
    assert space.panels == ((0, 1),)
    cache = single_bin_cache(scen, -12.0, 40.0, 1e-15)  # the only path is 10° off the shared azimuth
    for search in (
        lambda ev: coordinate_descent(ev, restarts=2, seed=1),
        lambda ev: differential_evolution(ev, time_budget_s=1.0, seed=0),
    ):
        ev = NetworkEvaluator(scen, 1, cache, space, KPIConfig(), "sinr")
        result = search(ev)
        a, b = (space.cells[p].config(result.config[p]) for p in (0, 1))
        assert a["azimuth_deg"] == b["azimuth_deg"]
        assert a["mech_tilt_deg"] - 4.0 == b["mech_tilt_deg"] - 2.0  # the panel tilts as one
        for p in (0, 1):
            assert space.tilt_ok(p, result.config[p])
    # coordinate descent did turn the panel towards the path
    ev = NetworkEvaluator(scen, 1, cache, space, KPIConfig(), "sinr")
    result = coordinate_descent(ev, restarts=1)
    assert space.cells[0].config(result.config[0])["azimuth_deg"] != 60.0


def _four_cells(root: Path):
    """The tiny scenario with two more 3.5 GHz cells (13, 14) on the same site, other azimuths."""
    import pandas as pd

    from rflscm.data import read_table, write_table
    from rflscm.data.examples import tiny_scenario

    tiny_scenario(root, seed=1)
    for name in ("cells_round1.csv", "cells_round2.csv"):
        cells = read_table(root / name)
        extra = []
        for cell, az in ((13, 180.0), (14, 300.0)):
            row = cells[cells["cell_id"] == 11].copy()
            row["cell_id"], row["azimuth_deg"], row["x"] = cell, az, row["x"] + cell
            extra.append(row)
        write_table(pd.concat([cells, *extra], ignore_index=True), root / name)
    return load(root)


@pytest.mark.parametrize("objective", ["coverage", "sinr", "weighted"])
def test_moves_scored_on_the_grids_in_reach_equal_the_whole_network_scored_again(tmp_path: Path, objective) -> None:
    from rflscm.eval.cache import ScenarioAPS
    from rflscm.network.search import _moves

    scen = _four_cells(tmp_path / "four")
    cells, grids = scen.cell_ids(), scen.grid_ids()
    rng = np.random.default_rng(0)
    known = np.array([[1, 1, 0], [1, 0, 1], [0, 1, 1], [1, 0, 0]], dtype=bool)  # no cell reaches every grid
    bins = [np.sort(rng.choice(GRID.num_bins, 6, replace=False)) for _ in cells]
    aps = [torch.as_tensor(10.0 ** rng.uniform(-14, -10, (int(k.sum()), 6)), dtype=torch.float32) for k in known]
    cache = ScenarioAPS(cells, grids, bins, aps, known, GRID, "synthetic")
    space = build_space(NO_STEP, scen.cells[1], scen.meta.codebooks)
    ev = NetworkEvaluator(scen, 1, cache, space, KPIConfig(threshold_dbm=-100.0), objective)
    assert all(r is not None for r in ev._rows)  # the local path is the one under test
    checked = 0
    for pos in range(len(cells)):
        for var in range(4):
            moves = _moves(ev, pos, var)
            if len(moves) < 2:
                continue
            scores = ev.score_moves(moves)
            base = list(ev.config)
            for k, move in enumerate(moves):
                config = list(base)
                for p, i in move.items():
                    config[p] = i
                ev.set_config(config)
                assert float(scores[k]) == pytest.approx(ev.score(), rel=1e-6, abs=1e-6), (pos, var, k)  # float32 KPIs
                ev.set_config(base)
                if move[pos] == base[pos]:
                    assert float(scores[k]) == ev.score()  # the present state scores the current objective
                checked += 1
    assert checked > 20
