"""The unseen-grid blend (``corrections.unseen_blend_grids``, issue 28): grids held out of the field's training choose
how much of the nearest anchored grid's APS a grid without reports takes."""

from __future__ import annotations

import dataclasses
import io

import numpy as np
import pytest
import torch
from tiny_rflscm import tiny_config

from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.errors import CheckpointError, ConfigError
from rflscm.geometry import AngleGrid
from rflscm.models.pairs import PairData
from rflscm.models.rflscm import RFLSCM
from rflscm.models.rflscm.config import CorrectionsConfig
from rflscm.models.rflscm.corrections import (
    BLEND_WEIGHTS,
    UNSEEN_WEIGHT,
    PairCorrections,
    blend_grids,
    choose_blend,
)
from rflscm.train import fit

GRID = AngleGrid.full_sphere(10, 12)

pytestmark = pytest.mark.usefixtures("one_thread")


def test_the_weight_whose_blend_explains_the_reports_is_chosen() -> None:
    own = torch.full((3, 4), 2.0)
    nearest = torch.full((3, 4), 0.5)
    measured = 0.7 * own + 0.3 * nearest
    mask = torch.ones(3, 4, dtype=torch.bool)
    weight, scores = choose_blend(own, nearest, measured, mask)
    assert weight == 0.3 and scores[0.3] < 1e-6 < scores[0.0] and sorted(scores) == list(BLEND_WEIGHTS)
    # only the masked reports count: the unmasked ones would ask for the nearest grid alone
    measured[:, 2:] = nearest[:, 2:]
    mask[:, 2:] = False
    assert choose_blend(own, nearest, measured, mask)[0] == 0.3
    assert choose_blend(own, nearest, measured, torch.zeros_like(mask)) == (0.0, {})


def test_a_tie_keeps_the_smaller_weight() -> None:
    same = torch.ones(2, 3)
    weight, scores = choose_blend(same, same, same, torch.ones(2, 3, dtype=torch.bool))
    assert weight == 0.0 and set(scores.values()) == {0.0}


def pair_data(grids: list[int], reported: list[bool]) -> PairData:
    p = len(grids)
    rsrp = torch.ones(p, 2)
    rsrp[~torch.tensor(reported)] = float("nan")
    return PairData(
        cell_index=torch.zeros(p, dtype=torch.long),
        grid_ids=np.asarray(grids, np.int64),
        grid_xyz=torch.zeros(p, 3),
        rsrp=rsrp,
        beam_mask=torch.ones(p, 2, dtype=torch.bool),
        val_mask=torch.zeros(p, 2, dtype=torch.bool),
        x_scale=torch.ones(p),
        bound=torch.full((p, 2), float("nan")),
        val_pairs=torch.zeros(0, dtype=torch.long),
    )


def test_the_held_out_grids_are_a_seeded_share_of_the_reported_grids() -> None:
    d = pair_data([1, 2, 3, 4, 5, 6, 7, 8, 8, 9], [True] * 9 + [False])  # grid 9 has no report
    held = blend_grids(d, 0.25, seed=0)
    assert len(held) == 2 and set(held) <= set(range(1, 9)) and list(held) == sorted(held)
    assert list(blend_grids(d, 0.25, seed=0)) == list(held) and list(blend_grids(d, 0.25, seed=1)) != list(held)
    assert blend_grids(d, 0.0, seed=0).size == 0
    assert len(blend_grids(d, 0.99, seed=0)) == 7  # one grid is always trained on
    assert blend_grids(pair_data([4], [True]), 0.5, seed=0).size == 0


@pytest.mark.parametrize("share", [-0.1, 1.0])
def test_a_share_outside_zero_to_one_is_refused_in_one_line(share: float) -> None:
    with pytest.raises(ConfigError, match="unseen_blend_grids"):
        CorrectionsConfig(unseen_blend_grids=share)
    assert CorrectionsConfig(unseen_blend_grids=None).unseen_blend_grids is None  # no blend


@pytest.mark.parametrize(("share", "weight"), [(0.0, UNSEEN_WEIGHT), (None, 0.0)])
def test_without_a_hold_out_the_weight_is_the_constant_or_none(tmp_path, share, weight) -> None:
    scenario = load_scenario(tiny_scenario(tmp_path, seed=0))
    config = tiny_config(corrections={"unseen_blend_grids": share})
    plan = RFLSCM.build(config, GRID).prepare(scenario)
    model = RFLSCM.build(config, GRID)
    fit(model, scenario, progress=False)
    d = model._training().data
    assert model._blend_grids.size == 0 and len(plan.pairs) == int(d.beam_mask.any(1).sum())  # every grid trains
    assert model.corrections.unseen_weight == weight
    assert ("unseen_blend" in model.run_info) == (share is not None)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    scenario = load_scenario(tiny_scenario(tmp_path_factory.mktemp("blend"), seed=0))
    config = tiny_config(corrections={"unseen_blend_grids": 0.3})
    plan = RFLSCM.build(config, GRID).prepare(scenario)  # the training plan fit follows (prepare is deterministic)
    torch.manual_seed(0)
    model = RFLSCM.build(config, GRID)
    fit(model, scenario, progress=False)
    return scenario, model, plan


def test_the_held_out_grids_are_not_trained_on_but_are_corrected(trained) -> None:
    _, model, plan = trained
    d = model._training().data
    held = model._blend_grids
    assert held.size and not np.isin(d.grid_ids[plan.pairs.numpy()], held).any()
    anchored = model.corrections.anchors.index.get_level_values("grid_id")
    assert np.isin(held, anchored).all()  # their pairs get anchors after training like every other pair
    info = model.run_info["unseen_blend"]
    assert info["held_out_grids"] == held.size and info["held_out_pairs"] > 0
    assert info["weight"] in BLEND_WEIGHTS and len(info["mae_db"]) == len(BLEND_WEIGHTS)
    assert model.corrections.unseen_weight == info["weight"]


def test_a_grid_without_reports_blends_its_aps_with_the_nearest_anchored_grids(trained) -> None:
    # APS values are ~1e-8 path gains: every comparison is relative (atol 0)
    _, model, _ = trained
    fitted = model.corrections
    cells = np.asarray(model.scene.cell_ids[:2], np.int64)
    near_grid = int(model.corrections.anchors.xs(int(cells[0]), level="cell_id").index[0])
    xyz = model.scene.grid_positions(np.array([near_grid])) + np.array([[0.5, 0.5, 0.0]])
    at = np.repeat(xyz, 2, axis=0)
    unseen = np.array([10**6, 10**6])  # a grid id no pair has: an unseen grid
    try:
        model.corrections = PairCorrections(fitted.levels, fitted.anchors, fitted.posterior, None, 0.0)
        own = model.aps(cells, unseen, at)
        model.corrections = PairCorrections(fitted.levels, fitted.anchors, fitted.posterior, None, 0.4)
        blended = model.aps(cells, unseen, at)
    finally:
        model.corrections = fitted
    near = np.array([model._nearest_anchored(cells[i : i + 1], xyz)[0] for i in range(2)])
    assert near[0] == near_grid
    nearest = model.aps(cells, near)
    assert not torch.allclose(own, nearest, rtol=1e-3, atol=0.0)  # the blend is no copy of either
    torch.testing.assert_close(blended, 0.6 * own + 0.4 * nearest, rtol=1e-5, atol=0.0)
    # far from every anchored grid there is nothing near to borrow from: the grid's own APS
    far = at + np.array([[200.0, 0.0, 0.0]])  # the tiny scene's anchored grids are ~50 m apart: 150 m reach
    try:
        model.corrections = PairCorrections(fitted.levels, fitted.anchors, fitted.posterior, None, 0.0)
        far_own = model.aps(cells, unseen, far)
        assert bool((far_own.sum(1) > 0).all())
        model.corrections = PairCorrections(fitted.levels, fitted.anchors, fitted.posterior, None, 0.4)
        torch.testing.assert_close(model.aps(cells, unseen, far), far_own, rtol=1e-5, atol=0.0)
    finally:
        model.corrections = fitted
    # a grid with anchors keeps its own corrected APS (its render as the pass kept it, whatever the weight)
    seen = model.aps(cells[:1], np.array([near_grid]))
    model.corrections = dataclasses.replace(fitted, unseen_weight=0.4)
    try:
        torch.testing.assert_close(model.aps(cells[:1], np.array([near_grid])), seen, rtol=1e-5, atol=0.0)
    finally:
        model.corrections = fitted


def test_the_weight_survives_a_save_and_a_damaged_one_is_refused() -> None:
    corr = PairCorrections(unseen_weight=0.7)
    buf = io.BytesIO()
    torch.save(corr.to_state(), buf)
    buf.seek(0)
    state = torch.load(buf, weights_only=True)
    assert PairCorrections.from_state(state, 4).unseen_weight == pytest.approx(0.7)
    state.pop("unseen_weight")  # a checkpoint written before the blend: no blend
    assert PairCorrections.from_state(state, 4).unseen_weight == 0.0
    for bad in (torch.tensor(1.5), torch.tensor([0.1, 0.2]), "x"):
        with pytest.raises(CheckpointError, match="blend weight"):
            PairCorrections.from_state({**state, "unseen_weight": bad}, 4)


def test_a_saved_model_predicts_the_same_blend(trained, tmp_path) -> None:
    from rflscm.models import load_model

    scenario, model, _ = trained
    fitted = model.corrections
    model.corrections = PairCorrections(fitted.levels, fitted.anchors, fitted.posterior, None, 0.4)
    try:
        path = model.save(tmp_path / "blend.ckpt")
        cells = np.asarray(model.scene.cell_ids[:2], np.int64)
        near_grid = int(model.corrections.anchors.xs(int(cells[0]), level="cell_id").index[0])
        at = np.repeat(model.scene.grid_positions(np.array([near_grid])) + np.array([[20.0, 0.0, 0.0]]), 2, axis=0)
        expected = model.aps(cells, np.array([10**6, 10**6]), at)
    finally:
        model.corrections = fitted
    loaded = load_model(path, scenario)
    assert loaded.corrections.unseen_weight == 0.4  # exactly: a loaded model predicts the same
    assert loaded.run_info["unseen_blend"] == model.run_info["unseen_blend"]
    torch.testing.assert_close(loaded.aps(cells, np.array([10**6, 10**6]), at), expected, rtol=1e-5, atol=0.0)
    loaded.corrections.unseen_weight = 0.0
    assert not torch.allclose(
        expected, loaded.aps(cells, np.array([10**6, 10**6]), at), rtol=1e-3, atol=0.0
    )  # it did blend


def test_without_anchors_there_is_nothing_to_blend_with(tmp_path) -> None:
    scenario = load_scenario(tiny_scenario(tmp_path, seed=0))
    model = RFLSCM.build(tiny_config(corrections={"unseen_blend_grids": 0.3, "pair_anchors": False}), GRID)
    fit(model, scenario, progress=False)
    assert model.corrections.anchors is None and model.corrections.unseen_weight == 0.0
    assert model.run_info["unseen_blend"]["held_out_pairs"] == 0.0
    cells = np.asarray(model.scene.cell_ids[:1], np.int64)
    assert model.aps(cells, np.array([10**6]), np.array([[0.0, 0.0, 1.5]])).shape[0] == 1
