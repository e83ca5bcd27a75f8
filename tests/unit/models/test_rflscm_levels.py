"""RF-LSCM's level correction (per cell and beam type, the median error on reported round-1 training beams) and
its pair anchors (per training pair, the mean error that remains)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pandas as pd
import pytest
import torch
from tiny_rflscm import tiny_config

from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.geometry import AngleGrid
from rflscm.models import load_model
from rflscm.models.rflscm import RFLSCM
from rflscm.models.rflscm import corrections as corrections_module
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
    import rflscm.models.rflscm.corrections as module

    monkeypatch.setattr(module, "LEVEL_PAIRS_PER_CELL", 10**6)  # measure on every pair: exact medians
    torch.manual_seed(0)
    model = RFLSCM.build(
        tiny_config(train={"val_pairs": 0}, corrections={"pair_anchors": False, "pair_posterior": False}), GRID
    )  # cell levels alone
    fit(model, scenario, progress=False)
    levels = model.corrections.levels
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
    assert isinstance(loaded, RFLSCM) and torch.equal(loaded.corrections.levels, levels.cpu())
    pairs, _ = scenario.rsrp_table(1, "csi")
    pairs = pairs.reset_index(drop=True)
    np.testing.assert_allclose(
        loaded.predict_rsrp(scenario, 1, "csi", pairs), model.predict_rsrp(scenario, 1, "csi", pairs), atol=1e-4
    )


def corrected_residuals_without(model: RFLSCM, scenario) -> dict[tuple[int, str], np.ndarray]:
    saved, model.corrections.levels = model.corrections.levels, torch.zeros_like(model.corrections.levels)
    try:
        return corrected_residuals(model, scenario)
    finally:
        model.corrections.levels = saved


def test_the_correction_follows_the_weights_and_can_be_switched_off(scenario) -> None:
    torch.manual_seed(0)
    model = RFLSCM.build(tiny_config(train={"val_pairs": 0, "steps": 4}), GRID)
    fit(model, scenario, progress=False)
    first = model.corrections.levels.clone()
    with torch.no_grad():
        for stage in model.all_stages():
            stage.decoder.scale_power(10.0)  # +10 dB everywhere: the correction must take it back
    assert torch.equal(model.corrections.levels, first)  # fitted once: moved weights do not refit it in aps
    model.finish_training()
    assert torch.allclose(model.corrections.levels, first - 10.0, atol=0.05)
    off = RFLSCM.build(tiny_config(train={"val_pairs": 0, "steps": 4}, corrections={"calibrate_levels": False}), GRID)
    fit(off, scenario, progress=False)
    assert off.corrections.levels is None


def test_evaluation_through_the_aps_cache_sees_the_csi_rs_correction(scenario) -> None:
    """Evaluation and `predict` wrap the model in an APS cache: its RSRP must carry the same per-beam-type levels."""
    from rflscm.eval.cache import APSCache

    torch.manual_seed(0)
    model = RFLSCM.build(tiny_config(train={"val_pairs": 0, "steps": 4}), GRID)
    fit(model, scenario, progress=False)
    levels = model.corrections.levels
    assert levels is not None and bool(((levels[:, 1] - levels[:, 0]).abs() > 0.1).any())
    for beam_type in ("ssb", "csi"):
        pairs = scenario.rsrp_table(1, beam_type)[0].reset_index(drop=True)
        np.testing.assert_allclose(
            APSCache(model).predict_rsrp(scenario, 1, beam_type, pairs),
            model.predict_rsrp(scenario, 1, beam_type, pairs),
            atol=1e-4,
        )


def test_pair_anchors_centre_each_training_pairs_errors_in_both_rounds_and_survive_a_checkpoint(
    scenario, tmp_path, monkeypatch
) -> None:
    """Each pair's own mean error (the pull toward the cell's mean left out: test_anchors.py tests it)."""
    monkeypatch.setattr(corrections_module, "shrunk_anchors", lambda anchor, *_: (anchor, math.nan))
    torch.manual_seed(0)
    model = RFLSCM.build(tiny_config(train={"val_pairs": 0, "steps": 4}, corrections={"pair_posterior": False}), GRID)
    fit(model, scenario, progress=False)
    anchors = model.corrections.anchors
    assert anchors is not None and len(anchors) > 0 and float(anchors.abs().max()) > 0.5
    # round 1: each pair's mean error over its reported beams (SSB and CSI-RS pooled) is now 0
    frames = []
    for beam_type in ("ssb", "csi"):
        pairs, measured = scenario.rsrp_table(1, beam_type)
        pairs = pairs.reset_index(drop=True)
        pred = model.predict_rsrp(scenario, 1, beam_type, pairs)[:, : measured.shape[1]]
        diff = measured - pred
        rows, beams = np.nonzero(np.isfinite(diff))
        frames.append(
            pd.DataFrame(
                {
                    "cell_id": pairs["cell_id"].to_numpy()[rows],
                    "grid_id": pairs["grid_id"].to_numpy()[rows],
                    "err": diff[rows, beams],
                }
            )
        )
    means = pd.concat(frames).groupby(["cell_id", "grid_id"])["err"].mean()
    assert len(means) == len(anchors) and float(means.abs().max()) < 0.05
    # round 2 (the changed antennas): the same pair moves by its anchor; a grid never measured does not move
    pairs = pd.DataFrame(
        {"cell_id": anchors.index.get_level_values(0)[:5], "grid_id": anchors.index.get_level_values(1)[:5]}
    )
    saved = model.corrections.anchors
    with_anchor = model.predict_rsrp(scenario, 2, "ssb", pairs)
    fitted = model.corrections
    model.corrections = dataclasses.replace(fitted, anchors=None)
    without = model.predict_rsrp(scenario, 2, "ssb", pairs)
    model.corrections = fitted
    np.testing.assert_allclose(
        with_anchor - without, np.repeat(anchors.to_numpy()[:5, None], without.shape[1], 1), atol=1e-3
    )
    cell = int(pairs["cell_id"][0])
    measured_grids = set(anchors.loc[cell].index)
    unmeasured = [g for g in scenario.grid_ids() if int(g) not in measured_grids][:1]
    if unmeasured:
        lone = pd.DataFrame({"cell_id": [cell], "grid_id": unmeasured})
        assert model.corrections.anchors is saved and anchors.reindex(pd.MultiIndex.from_frame(lone)).isna().all()
    model.save(tmp_path / "a.ckpt")
    loaded = load_model(tmp_path / "a.ckpt")
    pd.testing.assert_series_equal(loaded.corrections.anchors, anchors, check_exact=False, atol=1e-5)
    np.testing.assert_allclose(loaded.predict_rsrp(scenario, 2, "ssb", pairs), with_anchor, atol=1e-4)


def test_pair_anchors_can_be_switched_off_and_leave_validation_alone(scenario) -> None:
    runs = {}
    for on in (True, False):
        torch.manual_seed(0)
        model = RFLSCM.build(tiny_config(train={"steps": 4}, corrections={"pair_anchors": on}), GRID)
        summary = fit(model, scenario, progress=False)
        runs[on] = (model, summary)
    assert runs[False][0].corrections.anchors is None
    assert runs[True][0].corrections.anchors is not None
    # training and the held-aside validation score (the field alone) are the same either way
    assert runs[True][1]["final_loss"] == runs[False][1]["final_loss"]
    assert runs[True][1]["val_mae_db"] == runs[False][1]["val_mae_db"]


def test_damaged_pair_anchors_in_a_checkpoint_are_refused_in_one_line() -> None:
    from rflscm.errors import CheckpointError
    from rflscm.models.rflscm.corrections import _anchors_from_state

    good = {"cell_id": torch.tensor([1, 2]), "grid_id": torch.tensor([5, 6]), "anchor_db": torch.tensor([0.5, -1.0])}
    assert _anchors_from_state(good).loc[(2, 6)] == -1.0 and _anchors_from_state(None) is None
    for bad in (
        {"cell_id": good["cell_id"]},
        {**good, "grid_id": torch.tensor([5])},
        {**good, "anchor_db": torch.tensor([float("nan"), 0.0])},
        [1, 2],
    ):
        with pytest.raises(CheckpointError, match="pair anchors are damaged"):
            _anchors_from_state(bad)


def test_a_pair_round_1_did_not_report_gets_the_median_csi_rs_level_correction(scenario) -> None:
    """The cell's CSI-RS correction (relative to SSB) was fitted on pairs round 1 reported; a pair it did not report
    at a grid it visited is held to round 1's silence (its cap), so its CSI-RS prediction carries the median of the
    cells' corrections instead of its cell's own (measured on two ideal-regime cities, DECISIONS)."""
    from rflscm.models.rflscm.corrections import RoundOneCensor

    torch.manual_seed(0)
    model = RFLSCM.build(tiny_config(train={"val_pairs": 0, "steps": 4}), GRID)
    fit(model, scenario, progress=False)
    cells = model.scene.cell_ids[:2]
    grids = np.array([model.scene.grid_ids[0], model.scene.grid_ids[0]])
    offsets = model.corrections.level_offset_db(model.scene.cell_index(cells), "csi")
    assert offsets is not None and bool((np.abs(offsets) > 0.1).any())
    reported = pd.MultiIndex.from_arrays([cells[:1], grids[:1]], names=["cell_id", "grid_id"])
    model.corrections.censor = RoundOneCensor(reported, grids[:1], -120.0)  # the second cell silent at the grid
    every = model.corrections.level_offset_db(np.arange(len(model.scene.cell_ids)), "csi")
    assert every is not None and abs(float(np.median(every)) - offsets[1]) > 0.1  # the test can tell them apart
    got = model.level_offset_db(cells, "csi", grids)
    np.testing.assert_allclose(got, [offsets[0], np.median(every)])
    model.corrections.censor = None  # no silence table (rule sinr): every rendered pair keeps its cell's correction
    np.testing.assert_allclose(model.level_offset_db(cells, "csi", grids), offsets)
