"""The true APS reader and the oracle model (the evaluation floor)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from rflscm.data import load_scenario
from rflscm.errors import DataError
from rflscm.eval.oracle import OracleModel
from rflscm.geometry import AngleGrid
from rflscm.models.base import MODEL_REGISTRY, LSCMModel, UnsupportedError
from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario
from rflscm.sim.truth import load_true_aps

GRID = AngleGrid(num_el=31, num_az=36, el_min_deg=-90.0, el_step_deg=6.0)
CONFIG = SimulationConfig(
    num_sites=2, max_grids=40, seed=4, site_radius_m=120.0, angle_grid=GRID, point_cloud_points_per_m2=0.05
)


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    out = tmp_path_factory.mktemp("truth") / "sc"
    build_scenario(ProceduralCity(seed=3, size_m=240.0, num_buildings=12), CONFIG, out, progress=False)
    return load_scenario(out)


def test_true_aps_dense_matches_the_sparse_table(scenario) -> None:
    truth = load_true_aps(scenario)
    assert truth.angle_grid == GRID
    table = pd.read_parquet(scenario.root / "truth" / "aps.parquet")
    cells, grids = scenario.cell_ids()[[0, 3, 3]], scenario.grid_ids()[[5, 5, 17]]
    dense = truth.aps(cells, grids)
    assert dense.shape == (3, GRID.num_bins) and dense.dtype == torch.float32
    for i, (c, g) in enumerate(zip(cells, grids, strict=True)):
        rows = table[(table["cell_id"] == c) & (table["grid_id"] == g)]
        expected = np.zeros(GRID.num_bins)
        expected[rows["bin"].to_numpy()] = rows["power_lin"].to_numpy()
        np.testing.assert_allclose(dense[i].double().numpy(), expected, rtol=1e-6)
    assert dense.sum() > 0


def test_rebinning_onto_another_grid_keeps_the_total_power(scenario) -> None:
    native = load_true_aps(scenario)
    coarse = load_true_aps(scenario, AngleGrid(num_el=10, num_az=12, el_min_deg=-90.0, el_step_deg=20.0))
    cells = np.repeat(scenario.cell_ids(), 3)
    grids = np.tile(scenario.grid_ids()[:3], len(scenario.cell_ids()))
    a, b = native.aps(cells, grids, dtype=torch.float64), coarse.aps(cells, grids, dtype=torch.float64)
    assert b.shape[1] == 120
    np.testing.assert_allclose(a.sum(1).numpy(), b.sum(1).numpy(), rtol=1e-5)  # float32 paths on disk


def test_unknown_pairs_raise_unsupported(scenario) -> None:
    truth = load_true_aps(scenario)
    with pytest.raises(UnsupportedError, match="cell 999999"):
        truth.aps(np.array([999999]), scenario.grid_ids()[:1])
    with pytest.raises(UnsupportedError, match="grid"):
        truth.aps(scenario.cell_ids()[:1], np.array([-5]))


def subset(scenario, cell_ids: np.ndarray, grid_ids: np.ndarray):
    """``scenario`` restricted to some cells and grids, as the bench harness cuts one."""
    m = scenario.measurements
    rows = m["cell_id"].isin(cell_ids).to_numpy() & m["grid_id"].isin(grid_ids).to_numpy()
    return dataclasses.replace(
        scenario,
        cells={r: t[t["cell_id"].isin(cell_ids)].reset_index(drop=True) for r, t in scenario.cells.items()},
        grids=scenario.grids[scenario.grids["grid_id"].isin(grid_ids)].reset_index(drop=True),
        measurements=m[rows].reset_index(drop=True),
    )


@pytest.mark.parametrize(
    "grid", [None, AngleGrid(num_el=10, num_az=12, el_min_deg=-90.0, el_step_deg=20.0)], ids=["native", "rebinned"]
)
def test_oracle_of_a_subset_scenario_matches_the_full_scenario_by_id(scenario, grid, tmp_path: Path) -> None:
    # every other cell and every third grid: ids left out lie between and around the kept ones, so
    # truth rows matched by position instead of by id would land on a kept neighbour
    cells, grids = scenario.cell_ids()[1::2], scenario.grid_ids()[1::3]
    sub = subset(scenario, cells, grids)
    assert len(sub.cell_ids()) < len(scenario.cell_ids()) and len(sub.grid_ids()) < len(scenario.grid_ids())
    c, g = np.repeat(cells, len(grids)), np.tile(grids, len(cells))
    expected = load_true_aps(scenario, grid).aps(c, g, dtype=torch.float64)
    assert (expected.sum(1) > 0).sum() >= 10  # enough pairs that some path reaches
    torch.testing.assert_close(load_true_aps(sub, grid).aps(c, g, dtype=torch.float64), expected, rtol=0, atol=0)

    oracle = OracleModel(grid or GRID, "cpu").read(sub)
    assert oracle.fingerprint == sub.fingerprint()
    torch.testing.assert_close(oracle.aps(c, g).double(), expected.float().double(), rtol=0, atol=0)
    left_out = np.setdiff1d(scenario.cell_ids(), cells)[:1]
    with pytest.raises(UnsupportedError, match=f"cell {left_out[0]}"):
        oracle.aps(left_out, grids[:1])


def test_scenario_without_truth_is_a_data_error(scenario) -> None:
    no_truth = dataclasses.replace(scenario, meta=dataclasses.replace(scenario.meta, truth=None))
    with pytest.raises(DataError, match="no truth folder"):
        load_true_aps(no_truth)


def test_oracle_is_not_a_registered_model_and_predicts_the_noiseless_rsrp_up_to_binning(
    scenario, tmp_path: Path
) -> None:
    assert "oracle" not in MODEL_REGISTRY
    model = OracleModel.for_scenario(scenario, GRID)
    assert model.fingerprint == scenario.fingerprint()
    pairs, _ = scenario.rsrp_table(1, "ssb")
    predicted = model.predict_rsrp(scenario, 1, "ssb", pairs)
    truth = pd.read_parquet(scenario.root / "truth" / "rsrp_noiseless.parquet")
    truth = truth[(truth["round"] == 1) & (truth["beam_type"] == "ssb")]
    wide = truth.pivot_table(index=["cell_id", "grid_id"], columns="beam_id", values="rsrp_dbm")
    exact = wide.loc[list(zip(pairs["cell_id"], pairs["grid_id"], strict=True))].to_numpy()
    ok = exact >= -120
    err = np.abs(predicted[ok] - exact[ok])
    assert np.median(err) < 1.0  # a coarse 6° × 10° grid here; the default grid is finer
    # an evaluation device, not a model: nothing to train, save or load
    assert not isinstance(model, LSCMModel) and not hasattr(model, "save") and not hasattr(model, "fit")


def test_oracle_on_a_finer_grid_rebins_paths(scenario) -> None:
    fine = AngleGrid(num_el=61, num_az=72, el_min_deg=-90.0, el_step_deg=3.0)
    model = OracleModel(fine, "cpu").read(scenario)
    pair = (scenario.cell_ids(), np.repeat(scenario.grid_ids()[:1], len(scenario.cell_ids())))
    aps = model.aps(*pair)
    assert aps.shape == (len(pair[0]), fine.num_bins)
    coarse = OracleModel.for_scenario(scenario, GRID).aps(*pair)
    torch.testing.assert_close(aps.double().sum(1), coarse.double().sum(1), rtol=1e-4, atol=0)  # same paths, finer bins


def test_oracle_errors() -> None:
    with pytest.raises(UnsupportedError, match="has not read its truth"):
        OracleModel(GRID).aps(np.array([1]), np.array([1]))
