"""Metrics recomputed with independent formulas: MAE over reported beams, changed cells, the trivial
baseline, APS NMSE and the great-circle angular error."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.eval import metrics as M
from rflscm.geometry import AngleGrid


def test_mae_counts_only_reported_beams() -> None:
    measured = np.array([[-80.0, np.nan, -90.0], [np.nan, -70.0, np.nan]])
    predicted = np.array([[-82.0, -10.0, -89.0], [-75.0, -74.0, np.nan]])
    err = M.abs_error_db(predicted, measured)
    assert M.mae_db(err) == pytest.approx((2.0 + 1.0 + 4.0) / 3)  # the −10 dBm guess for a missing beam is ignored
    assert M.mae_db(err, np.array([False, True])) == pytest.approx(4.0)
    assert M.mae_db(err, np.array([False, False])) is None
    assert M.count_finite(err) == 3


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory):
    return load_scenario(tiny_scenario(tmp_path_factory.mktemp("metrics") / "tiny", seed=0))


def test_changed_cells_compare_antenna_and_codebooks(tiny) -> None:
    assert M.changed_cells(tiny, 1, 2).tolist() == [12]  # tiny: cell 12 tilts 6° further down in round 2
    assert M.changed_cells(tiny, 1, 1).tolist() == []
    assert M.changed_cells(tiny, 1, 3).tolist() == []  # no round 3: nothing to compare
    cells2 = tiny.cells[2].copy()
    cells2.loc[cells2["cell_id"] == 11, "csi_codebook"] = "ssb8"  # a codebook swap is a change too
    swapped = type(tiny)(tiny.root, tiny.meta, {1: tiny.cells[1], 2: cells2}, tiny.grids, tiny.measurements)
    assert M.changed_cells(swapped, 1, 2).tolist() == [11, 12]


def test_trivial_baseline_uses_pair_then_cell_then_overall_means(tiny) -> None:
    pairs, rsrp = tiny.rsrp_table(1, "ssb")
    row = int(np.flatnonzero((pairs["cell_id"] == 11) & (pairs["grid_id"] == 101))[0])
    query = pd.DataFrame({"cell_id": [11, 11, 99], "grid_id": [101, 555, 101]})
    pred = M.trivial_prediction(tiny, "ssb", query, 4)
    assert pred.shape == (3, 4)
    assert pred[0] == pytest.approx(np.full(4, np.nanmean(rsrp[row])))
    cell_rows = rsrp[(pairs["cell_id"] == 11).to_numpy()]
    assert pred[1, 0] == pytest.approx(np.mean([np.nanmean(r) for r in cell_rows]))  # unseen grid: the cell's mean
    assert pred[2, 0] == pytest.approx(np.mean([np.nanmean(r) for r in rsrp]))  # unknown cell: the overall mean


def test_aps_nmse_db() -> None:
    true = np.array([[0.0, 2.0, 0.0, 1.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    est = np.array([[0.0, 2.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]])
    db = M.aps_nmse_db(est, true)
    assert db[0] == -100.0  # exact: floored
    assert db[1] == pytest.approx(0.0)  # all-zero estimate: ‖x‖²/‖x‖²
    assert np.isnan(db[2])  # no true power: undefined


def _great_circle_deg(el1: float, az1: float, el2: float, az2: float) -> float:
    """Haversine, an independent formula."""
    e1, a1, e2, a2 = np.radians([el1, az1, el2, az2])
    h = np.sin((e2 - e1) / 2) ** 2 + np.cos(e1) * np.cos(e2) * np.sin((a2 - a1) / 2) ** 2
    return float(np.degrees(2 * np.arcsin(np.sqrt(h))))


def test_angle_error_is_power_weighted_great_circle() -> None:
    grid = AngleGrid(num_el=19, num_az=36, el_min_deg=-90.0, el_step_deg=10.0)

    def b(el_deg: float, az_deg: float) -> int:
        return int(grid.bin_of(np.radians([el_deg]), np.radians([az_deg]))[0])

    true = np.zeros((3, grid.num_bins))
    est = np.zeros_like(true)
    true[0, b(0, 0)], est[0, b(0, 0)] = 1.0, 5.0  # same bin, other power: 0°
    true[1, b(20, 40)], est[1, b(40, 100)] = 1.0, 1.0  # one path moved
    true[2, b(0, 0)], true[2, b(0, 180)] = 3.0, 1.0  # two true paths, the estimate finds the strong one
    est[2, b(0, 10)] = 1.0
    err = M.aps_angle_error_deg(est, true, grid, top_k=3)
    assert err[0] == pytest.approx(0.0, abs=1e-6)
    assert err[1] == pytest.approx(_great_circle_deg(20, 40, 40, 100))
    t_to_e = (3.0 * _great_circle_deg(0, 0, 0, 10) + 1.0 * _great_circle_deg(0, 180, 0, 10)) / 4.0
    e_to_t = _great_circle_deg(0, 10, 0, 0)
    assert err[2] == pytest.approx(0.5 * (t_to_e + e_to_t))
    assert np.isnan(M.aps_angle_error_deg(np.zeros((1, grid.num_bins)), true[:1], grid)[0])
