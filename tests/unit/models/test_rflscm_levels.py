"""RF-LSCM's level correction: per cell and beam type, the median error on reported round-1 training beams."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from tiny_rflscm import tiny_config

from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.geometry import AngleGrid
from rflscm.models import load_model
from rflscm.models.rflscm import RFLSCM
from rflscm.train import fit

GRID = AngleGrid.full_sphere(10, 12)
pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    return load_scenario(tiny_scenario(tmp_path_factory.mktemp("levels"), seed=0))


def corrected_residuals(model: RFLSCM, scenario) -> dict[tuple[int, str], np.ndarray]:
    """measured − predicted [dB] over every reported round-1 beam, per (cell, beam type), with the correction."""
    out: dict[tuple[int, str], np.ndarray] = {}
    for beam_type in ("ssb", "csi"):
        pairs, measured = scenario.rsrp_table(1, beam_type)
        pred = model.predict_rsrp(scenario, 1, beam_type, pairs.reset_index(drop=True))[:, : measured.shape[1]]
        for cell in np.unique(pairs["cell_id"]):
            rows = (pairs["cell_id"] == cell).to_numpy()
            diff = (measured[rows] - pred[rows]).ravel()
            out[(int(cell), beam_type)] = diff[np.isfinite(diff)]
    return out


def test_the_correction_centres_each_cells_round1_errors_and_survives_a_checkpoint(
    scenario, tmp_path, monkeypatch
) -> None:
    import rflscm.models.rflscm as module

    monkeypatch.setattr(module, "LEVEL_PAIRS_PER_CELL", 10**6)  # measure on every pair: exact medians
    torch.manual_seed(0)
    model = RFLSCM.build(tiny_config(train={"val_pairs": 0}), GRID)
    fit(model, scenario, progress=False)
    levels = model.levels
    assert levels is not None and levels.shape == (len(scenario.cell_ids()), 2)
    before = {k: v.copy() for k, v in corrected_residuals_without(model, scenario).items()}
    after = corrected_residuals(model, scenario)
    # measured on every reported beam, the correction moves each (cell, type) median error to 0 where the cell
    # has enough beams, and it was not 0 before
    centred = [k for k, v in after.items() if v.size >= 10]
    assert centred and all(abs(float(np.median(after[k]))) < 0.05 for k in centred)
    assert max(abs(float(np.median(before[k]))) for k in centred) > 0.5
    model.save(tmp_path / "m.ckpt")
    loaded = load_model(tmp_path / "m.ckpt")
    assert isinstance(loaded, RFLSCM) and torch.equal(loaded.levels, levels.cpu())
    pairs, _ = scenario.rsrp_table(1, "csi")
    pairs = pairs.reset_index(drop=True)
    np.testing.assert_allclose(
        loaded.predict_rsrp(scenario, 1, "csi", pairs), model.predict_rsrp(scenario, 1, "csi", pairs), atol=1e-4
    )


def corrected_residuals_without(model: RFLSCM, scenario) -> dict[tuple[int, str], np.ndarray]:
    saved, model.levels = model.levels, torch.zeros_like(model.levels)
    try:
        return corrected_residuals(model, scenario)
    finally:
        model.levels = saved


def test_the_correction_follows_the_weights_and_can_be_switched_off(scenario) -> None:
    torch.manual_seed(0)
    model = RFLSCM.build(tiny_config(train={"val_pairs": 0, "steps": 4}), GRID)
    fit(model, scenario, progress=False)
    first = model.current_levels().clone()
    with torch.no_grad():
        for stage in model.all_stages():
            stage.decoder.scale_power(10.0)  # +10 dB everywhere: the correction must take it back
    model.step += 1
    assert torch.allclose(model.current_levels(), first - 10.0, atol=0.05)
    off = RFLSCM.build(tiny_config(train={"val_pairs": 0, "steps": 4, "calibrate_levels": False}), GRID)
    fit(off, scenario, progress=False)
    assert off.current_levels() is None and off.levels is None


def test_evaluation_through_the_aps_cache_sees_the_csi_rs_correction(scenario) -> None:
    """Evaluation and `predict` wrap the model in an APS cache: its RSRP must carry the same per-beam-type levels."""
    from rflscm.eval.cache import APSCache

    torch.manual_seed(0)
    model = RFLSCM.build(tiny_config(train={"val_pairs": 0, "steps": 4}), GRID)
    fit(model, scenario, progress=False)
    levels = model.current_levels()
    assert levels is not None and bool(((levels[:, 1] - levels[:, 0]).abs() > 0.1).any())
    for beam_type in ("ssb", "csi"):
        pairs = scenario.rsrp_table(1, beam_type)[0].reset_index(drop=True)
        np.testing.assert_allclose(
            APSCache(model).predict_rsrp(scenario, 1, beam_type, pairs),
            model.predict_rsrp(scenario, 1, beam_type, pairs),
            atol=1e-4,
        )
