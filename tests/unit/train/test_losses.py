"""The LSCM loss (paper eqs. (19), (22)–(23)) in its linear and log forms."""

from __future__ import annotations

import math

import torch

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
    out = lscm_loss(pred, rsrp, mask, aps, scale, threshold=0.05, fidelity="log", sparsity_weight=0.1, penalty_weight=0.5, floor=0.0)
    fid = (math.log10(0.1) ** 2 + math.log10(2.0) ** 2) / 2  # bels², observed beams only
    pen = (math.log10(0.5 / 0.05) ** 2 + math.log10(1.0 / 0.05) ** 2) / 2  # missing beams above r_th
    sparsity = 0.1 * (3.0 / 2.0 + 1.0 / 1.0) / 2
    assert math.isclose(float(out["fidelity"]), fid, rel_tol=1e-5)
    assert math.isclose(float(out["penalty"]), pen, rel_tol=1e-5)
    assert math.isclose(float(out["sparsity"]), sparsity, rel_tol=1e-5)
    assert math.isclose(float(out["total"]), fid + sparsity + 0.5 * pen, rel_tol=1e-5)


def test_linear_form_terms() -> None:
    pred, rsrp, mask, aps, scale = setup()
    out = lscm_loss(pred, rsrp, mask, aps, scale, threshold=0.05, fidelity="linear", sparsity_weight=0.1, penalty_weight=0.5)
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
    out = lscm_loss(pred, rsrp, torch.ones(1, 3, dtype=torch.bool), torch.zeros(1, 1), torch.ones(1), 0.05, "log", 0.0, 0.5)
    out["total"].backward()
    assert pred.grad[0, 0] == 0 and pred.grad[0, 1] > 0 and pred.grad[0, 2] < 0


def test_mae_db() -> None:
    pred = torch.tensor([[1.0, 10.0, 5.0]])
    rsrp = torch.tensor([[10.0, 10.0, NAN]])
    assert math.isclose(float(mae_db(pred, rsrp, torch.ones(1, 3, dtype=torch.bool))), 5.0, rel_tol=1e-6)
    assert math.isnan(float(mae_db(pred, rsrp, torch.zeros(1, 3, dtype=torch.bool))))
