"""The LSCM loss (paper eqs. (19), (22)–(23)) in its linear and log forms."""

from __future__ import annotations

import math

import torch

from rflscm.models.rflscm.losses import LEVEL_KEPT
from rflscm.train import lscm_loss, mae_db

NAN = float("nan")


def setup():
    pred = torch.tensor([[1.0, 0.1, 0.02, 0.5], [2.0, 1.0, 1e-4, 0.0]])
    rsrp = torch.tensor([[1.0, 1.0, NAN, NAN], [1.0, NAN, NAN, 0.3]])
    mask = torch.tensor([[True, True, True, True], [True, True, True, False]])  # last beam of pair 2 absent
    aps = torch.tensor([[1.0, 2.0], [0.5, 0.5]])
    return pred, rsrp, mask, aps, torch.tensor([2.0, 1.0])


def test_log_form_terms() -> None:
    pred, rsrp, mask, aps, scale = setup()
    out = lscm_loss(
        pred, rsrp, mask, aps, scale, bound=0.05, fidelity="log", sparsity_weight=0.1, penalty_weight=0.5, floor=0.0
    )
    fid = (math.log10(0.1) ** 2 + math.log10(2.0) ** 2) / 2  # bels², observed beams only
    pen = (math.log10(0.5 / 0.05) ** 2 + math.log10(1.0 / 0.05) ** 2) / 2  # missing beams above r_th
    sparsity = 0.1 * (3.0 / 2.0 + 1.0 / 1.0) / 2
    assert math.isclose(float(out["fidelity"]), fid, rel_tol=1e-5)
    assert math.isclose(float(out["penalty"]), pen, rel_tol=1e-5)
    assert math.isclose(float(out["sparsity"]), sparsity, rel_tol=1e-5)
    assert math.isclose(float(out["total"]), fid + sparsity + 0.5 * pen, rel_tol=1e-5)


def test_linear_form_terms() -> None:
    pred, rsrp, mask, aps, scale = setup()
    out = lscm_loss(
        pred, rsrp, mask, aps, scale, bound=0.05, fidelity="linear", sparsity_weight=0.1, penalty_weight=0.5
    )
    assert math.isclose(float(out["fidelity"]), (0.9**2 + 1.0) / 2, rel_tol=1e-6)
    assert math.isclose(float(out["penalty"]), (0.45**2 + 0.95**2) / 2, rel_tol=1e-6)
    assert math.isclose(float(out["sparsity"]), 0.1 * 4.0 / 2, rel_tol=1e-6)


def test_penalty_is_one_sided() -> None:
    pred = torch.tensor([[0.01, 0.2]])
    rsrp = torch.tensor([[NAN, NAN]])
    mask = torch.ones(1, 2, dtype=torch.bool)
    for form in ("log", "linear"):
        below = lscm_loss(pred[:, :1], rsrp[:, :1], mask[:, :1], pred, torch.ones(1), 0.05, form)
        above = lscm_loss(pred[:, 1:], rsrp[:, 1:], mask[:, 1:], pred, torch.ones(1), 0.05, form)
        assert float(below["penalty"]) == 0.0 and float(above["penalty"]) > 0.0


def test_gradient_reaches_predictions_of_missing_beams_only_above_threshold() -> None:
    pred = torch.tensor([[0.01, 0.2, 1.0]], requires_grad=True)
    rsrp = torch.tensor([[NAN, NAN, 2.0]])
    out = lscm_loss(
        pred, rsrp, torch.ones(1, 3, dtype=torch.bool), torch.zeros(1, 1), torch.ones(1), 0.05, "log", 0.0, 0.5
    )
    out["total"].backward()
    assert pred.grad[0, 0] == 0 and pred.grad[0, 1] > 0 and pred.grad[0, 2] < 0


def test_mae_db() -> None:
    pred = torch.tensor([[1.0, 10.0, 5.0]])
    rsrp = torch.tensor([[10.0, 10.0, NAN]])
    assert math.isclose(float(mae_db(pred, rsrp, torch.ones(1, 3, dtype=torch.bool))), 5.0, rel_tol=1e-6)
    assert math.isnan(float(mae_db(pred, rsrp, torch.zeros(1, 3, dtype=torch.bool))))


def test_top_n_penalty_is_zero_for_a_prediction_that_respects_the_per_report_bound() -> None:
    """Top-2 reports: a missing beam of a full report is bounded by that report's weakest beam, not r_th."""
    import numpy as np
    import pandas as pd

    from rflscm.data.reporting import missing_bounds, reporting_from_dict

    rsrp_dbm = np.array([[-70.0, -80.0, NAN, NAN], [-95.0, NAN, NAN, NAN]])  # report 1 full, report 2 not
    pairs = pd.DataFrame({"cell_id": [1, 1], "grid_id": [5, 6]})
    toy = type("Toy", (), {})()
    toy.meta = type(
        "Meta",
        (),
        {"rsrp_threshold_dbm": -120.0, "reporting": reporting_from_dict({"csi": {"rule": "top_n", "top_n": 2}})},
    )()
    toy.num_beams = lambda cell, beam_type, round=1: 4
    bound_dbm = missing_bounds(toy, 1, "csi", pairs, rsrp_dbm)
    np.testing.assert_array_equal(bound_dbm, [[NAN, NAN, -80.0, -80.0], [NAN, -120.0, -120.0, -120.0]])
    to_lin = lambda dbm: torch.as_tensor(10.0 ** (np.asarray(dbm) / 10.0) / 1e-9, dtype=torch.float32)  # noqa: E731
    respecting = np.where(np.isnan(rsrp_dbm), bound_dbm - 0.5, rsrp_dbm)  # −80.5 dBm: above r_th, below the bound
    mask = torch.ones(2, 4, dtype=torch.bool)
    args = (to_lin(respecting), to_lin(rsrp_dbm), mask, torch.zeros(2, 1), torch.ones(2))
    for form in ("log", "linear"):
        assert float(lscm_loss(*args, bound=to_lin(bound_dbm), fidelity=form)["penalty"]) == 0.0
        assert float(lscm_loss(*args, bound=to_lin(-120.0), fidelity=form)["penalty"]) > 0.0  # r_th would punish it
        over = to_lin(np.where(np.isnan(rsrp_dbm), bound_dbm + 3.0, rsrp_dbm))
        assert float(lscm_loss(over, *args[1:], bound=to_lin(bound_dbm), fidelity=form)["penalty"]) > 0.0


def test_shape_form_moves_each_pair_by_its_shrunk_level() -> None:
    """``shape``: each pair's errors first move by b = (1 − s) ē; its fidelity is Σ (e − b)² and its missing-beam
    penalty reads the moved predictions."""
    pred, rsrp, mask, aps, scale = setup()
    out = lscm_loss(pred, rsrp, mask, aps, scale, 0.05, "shape", sparsity_weight=0.1, penalty_weight=0.5, floor=0.0)
    e1, e2 = [0.0, math.log10(0.1)], [math.log10(2.0)]
    b1, b2 = (1 - LEVEL_KEPT) * sum(e1) / 2, (1 - LEVEL_KEPT) * e2[0]
    fid = (sum((e - b1) ** 2 for e in e1) + (e2[0] - b2) ** 2) / 2
    pen = ((math.log10(0.5 / 0.05) - b1) ** 2 + (math.log10(1.0 / 0.05) - b2) ** 2) / 2
    assert math.isclose(float(out["fidelity"]), fid, rel_tol=1e-5)
    assert math.isclose(float(out["penalty"]), pen, rel_tol=1e-5)
    log = lscm_loss(pred, rsrp, mask, aps, scale, 0.05, "log", sparsity_weight=0.1, penalty_weight=0.5, floor=0.0)
    assert math.isclose(float(out["sparsity"]), float(log["sparsity"]))  # the APS itself is not moved


def test_shape_form_keeps_a_share_of_a_common_error_and_all_of_a_difference() -> None:
    """A pair whose k beams are all c bels off keeps the share s of its error whatever k; the gradient of a
    difference between its beams is the log form's."""
    c = 0.5
    for k in (1, 4, 40):
        common = torch.full((1, k), 10.0**c)
        out = lscm_loss(
            common,
            torch.ones(1, k),
            torch.ones(1, k, dtype=torch.bool),
            common,
            torch.ones(1),
            0.05,
            "shape",
            0.0,
            0.0,
            floor=0.0,
        )
        assert math.isclose(float(out["fidelity"]), k * (c * LEVEL_KEPT) ** 2, rel_tol=1e-5)
    k = 4
    rsrp = torch.ones(1, k)
    mask = torch.ones(1, k, dtype=torch.bool)
    spread = torch.tensor([[10.0**c, 10.0**-c, 1.0, 1.0]], requires_grad=True)  # no common error: b = 0
    grads = []
    for form in ("shape", "log"):
        lscm_loss(spread, rsrp, mask, spread, torch.ones(1), 0.05, form, 0.0, 0.0, floor=0.0)["total"].backward()
        grads.append(spread.grad.clone())
        spread.grad = None
    torch.testing.assert_close(grads[0], grads[1])
