"""Anchors interpolated to pairs without reports (:mod:`rflscm.models.rflscm.unseen`, issue 28)."""

from __future__ import annotations

import io

import numpy as np
import pandas as pd
import pytest
import torch

from rflscm.errors import CheckpointError
from rflscm.models.rflscm.corrections import PairCorrections
from rflscm.models.rflscm.unseen import AnchorField, fit_anchor_field


def smooth_anchors(seed: int = 0, grids: int = 300, noise_db: float = 0.3):
    """Two cells whose anchors vary smoothly over a 200 m square (a few dB over ~50 m), plus a little noise."""
    rng = np.random.default_rng(seed)
    xyz = np.concatenate([rng.uniform(0, 200, (grids, 2)), np.full((grids, 1), 1.5)], 1)
    cells = np.repeat([3, 7], grids)
    xyz = np.concatenate([xyz, xyz])
    phase = np.where(cells == 3, 0.0, 1.0)
    truth = 4.0 * np.sin(xyz[:, 0] / 30.0 + phase) * np.cos(xyz[:, 1] / 40.0)
    return cells, xyz, truth, truth + rng.normal(0.0, noise_db, len(truth))


def test_smooth_anchors_are_interpolated_to_grids_left_out() -> None:
    cells, xyz, truth, anchors = smooth_anchors()
    held = np.arange(len(cells)) % 5 == 0
    field = fit_anchor_field(cells[~held], xyz[~held], anchors[~held], np.full(int((~held).sum()), 4))
    scores = field.scores
    assert field.length_m > 0 and scores[(field.length_m, field.prior_weight)] < 0.5 * scores[(0.0, 0.0)]
    predicted = field.predict(cells[held], xyz[held])
    assert np.abs(predicted - truth[held]).mean() < 0.4 * np.abs(truth[held]).mean()
    # each cell is interpolated from its own anchors: swapping the cells' ids makes it worse
    swapped = field.predict(np.where(cells[held] == 3, 7, 3), xyz[held])
    assert np.abs(swapped - truth[held]).mean() > 2 * np.abs(predicted - truth[held]).mean()


def test_far_from_every_anchor_and_for_an_unknown_cell_the_level_alone_is_kept() -> None:
    cells, xyz, _, anchors = smooth_anchors()
    field = fit_anchor_field(cells, xyz, anchors, np.ones(len(cells)))
    assert field.length_m > 0
    far = np.array([[5000.0, 5000.0, 1.5], [100.0, 100.0, 1.5]])
    out = field.predict(np.array([3, 99]), far)
    assert out.tolist() == [0.0, 0.0]


def test_anchors_without_spatial_structure_switch_the_interpolation_off() -> None:
    rng = np.random.default_rng(1)
    cells, xyz, _, _ = smooth_anchors()
    field = fit_anchor_field(cells, xyz, rng.normal(0.0, 3.0, len(cells)), np.ones(len(cells)))
    assert field.length_m == 0 and min(field.scores, key=field.scores.__getitem__) == (0.0, 0.0)
    assert len(field.cell_ids) == 0 and field.predict(cells[:5], xyz[:5]).tolist() == [0.0] * 5


def test_the_leave_one_out_weights_each_pair_by_its_reported_beams() -> None:
    cells, xyz, _, anchors = smooth_anchors(noise_db=0.0)
    even = fit_anchor_field(cells, xyz, anchors, np.ones(len(cells))).scores
    skewed = fit_anchor_field(cells, xyz, anchors, np.arange(len(cells)) % 7 + 1.0).scores
    assert even != skewed


def test_pairs_with_an_anchor_keep_it_and_the_others_get_the_interpolated_one() -> None:
    cells, xyz, _, anchors = smooth_anchors()
    field = fit_anchor_field(cells, xyz, anchors, np.ones(len(cells)))
    assert field.length_m > 0
    grids = np.arange(len(cells)) % 300
    index = pd.MultiIndex.from_arrays([cells[:10], grids[:10]], names=["cell_id", "grid_id"])
    own = pd.Series(np.full(10, 6.0), index=index, name="anchor_db")
    corr = PairCorrections(anchors=own, unseen=field)
    aps = torch.ones(4, 3)
    ask_cells, ask_grids = np.array([3, 3, 3, 7]), np.array([0, 1, 500, 500])
    ask_xyz = np.stack([xyz[0], xyz[1], [60.0, 80.0, 1.5], [60.0, 80.0, 1.5]])
    out = 10 * np.log10(corr.apply(aps, np.zeros(4, np.int64), ask_cells, ask_grids, ask_xyz)[:, 0].numpy())
    expected = field.predict(ask_cells[2:], ask_xyz[2:])
    np.testing.assert_allclose(out, [6.0, 6.0, *expected], atol=1e-4)
    # without positions (or without the fitted field) a pair without an anchor keeps the level alone, as before
    plain = 10 * np.log10(corr.apply(aps, np.zeros(4, np.int64), ask_cells, ask_grids)[:, 0].numpy())
    np.testing.assert_allclose(plain, [6.0, 6.0, 0.0, 0.0], atol=1e-4)


def test_a_round_trip_through_torch_save_keeps_the_interpolation_and_damage_is_refused() -> None:
    cells, xyz, _, anchors = smooth_anchors()
    field = fit_anchor_field(cells, xyz, anchors, np.ones(len(cells)))
    assert field.length_m > 0
    index = pd.MultiIndex.from_arrays([cells[:3], np.arange(3)], names=["cell_id", "grid_id"])
    corr = PairCorrections(anchors=pd.Series(np.zeros(3), index=index, name="anchor_db"), unseen=field)
    buf = io.BytesIO()
    torch.save(corr.to_state(), buf)
    buf.seek(0)
    back = PairCorrections.from_state(torch.load(buf, weights_only=True), num_bins=3)
    assert back.unseen is not None
    ask = np.array([[60.0, 80.0, 1.5], [10.0, 190.0, 1.5]])
    np.testing.assert_array_equal(back.unseen.predict(np.array([3, 7]), ask), field.predict(np.array([3, 7]), ask))
    old = {k: v for k, v in corr.to_state().items() if k != "unseen"}  # a checkpoint from before: no interpolation
    assert PairCorrections.from_state(old, num_bins=3).unseen is None
    state = field.to_state()
    for damaged in ({**state, "kernel": torch.tensor([float("nan"), 1.0])}, {**state, "xyz": state["xyz"][:-1]}, {k: state[k] for k in ("xyz", "kernel")}):
        with pytest.raises(CheckpointError, match="unseen-grid anchors are damaged") as info:
            AnchorField.from_state(damaged)
        assert "\n" not in str(info.value)
