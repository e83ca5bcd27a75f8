"""RF-LSCM end to end on the tiny scenario: config, gradients, learning, resume, persistence, contract."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from tiny_rflscm import Interrupt, stop_at, tiny_config

from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.errors import CheckpointError, ConfigError
from rflscm.fields import TensorVM
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY, UnsupportedError, load_model
from rflscm.models.rflscm import RFLSCM
from rflscm.models.rflscm.config import RFLSCMConfig, load_rflscm_config, preset_path
from rflscm.models.rflscm.renderer import FILL_BLOCKS
from rflscm.train import fit

GRID = AngleGrid.full_sphere(10, 12)


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    return load_scenario(tiny_scenario(tmp_path_factory.mktemp("tiny"), seed=0))


def test_registered_and_built_from_presets(tmp_path) -> None:
    assert MODEL_REGISTRY["rflscm"] is RFLSCM
    quick, full = load_rflscm_config("quick"), load_rflscm_config("full")
    assert isinstance(quick, RFLSCMConfig) and quick != full and preset_path("quick").is_file()
    assert RFLSCM.build(None, GRID).config == RFLSCMConfig()
    path = tmp_path / "c.yaml"
    path.write_text("hitam:\n  top_k: 7\n")
    assert RFLSCM.build(str(path), GRID).config.hitam.top_k == 7
    with pytest.raises(ConfigError, match="valid keys"):
        RFLSCM.build({"hitam": {"topk": 3}}, GRID)
    with pytest.raises(ConfigError, match="preset"):
        RFLSCM.build("quickest", GRID)
    with pytest.raises(ConfigError, match="beta"):
        RFLSCM.build({"hitam": {"beta": 1}}, GRID)


def test_gradients_reach_every_parameter(scenario) -> None:
    model = RFLSCM.build(tiny_config(), GRID)
    model._prepare(scenario)
    groups = model.parameter_groups()
    assert set(groups) == {"tensors", "networks"}
    losses = model.training_losses(torch.arange(model._train.data.num_pairs), position=4.0)  # 0 < α < 1: both stages
    assert 0.0 < losses["alpha"] < 1.0
    losses["total"].backward()
    for name, p in model.stages.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    tensors = {id(p) for p in groups["tensors"]}
    for module in model.stages.modules():
        if isinstance(module, TensorVM):
            assert all(id(p) in tensors for p in module.parameters())


@pytest.mark.parametrize(("fidelity", "factor"), [("log", 8.0), ("shape", 4.0)])
def test_loss_falls_by_a_large_factor(scenario, fidelity: str, factor: float) -> None:
    """Full batches of the 6 pairs (the tiny data drops strong beams at random, so no missing-beam penalty).  The
    ``shape`` form starts lower: most of each pair's level error is profiled out of it."""
    cfg = tiny_config(
        train={
            "steps": 150,
            "val_every": 50,
            "batch_pairs": 6,
            "pairs_per_cell": 3,
            "lr": {"tensors": 0.01, "networks": 0.01},
        },
        hitam={"warmup_steps": 60, "ramp_steps": 20},
        loss={"missing_penalty": 0.0, "fidelity": fidelity},
    )
    history = []
    fit(RFLSCM.build(cfg, GRID), scenario, progress=False, callback=lambda m: history.append(m["total"]))
    first, last = np.mean(history[:3]), np.mean(history[-3:])
    assert last < first / factor, (first, last)


def killed_after_four_steps(scenario, ckpt) -> list[float]:
    """The tiny run's loss history; the same run killed after 4 steps leaves its checkpoint at ``ckpt``."""
    reference: list[float] = []
    fit(RFLSCM.build(tiny_config(), GRID), scenario, progress=False, callback=lambda m: reference.append(m["total"]))
    with pytest.raises(Interrupt):
        fit(RFLSCM.build(tiny_config(), GRID), scenario, progress=False, callback=stop_at(4), checkpoint_path=ckpt)
    return reference


def resumed(scenario, config: dict, ckpt) -> list[float]:
    """The loss history of a run of ``config`` resumed from ``ckpt``."""
    losses: list[float] = []
    run = dict(progress=False, checkpoint_path=ckpt, resume=True)
    fit(RFLSCM.build(config, GRID), scenario, callback=lambda m: losses.append(m["total"]), **run)
    return losses


def test_resume_continues_exactly(scenario, tmp_path) -> None:
    ckpt = tmp_path / "run.ckpt"
    reference = killed_after_four_steps(scenario, ckpt)
    assert resumed(scenario, tiny_config(), ckpt) == reference[4:]
    with pytest.raises(CheckpointError, match="another config"):
        resumed(scenario, tiny_config(decoder={"hidden": 8}), ckpt)


def test_resume_reads_an_option_added_since_the_checkpoint_as_its_default(scenario, tmp_path) -> None:
    from rflscm.models.base import content_hash

    ckpt = tmp_path / "old.ckpt"
    reference = killed_after_four_steps(scenario, ckpt)
    archive = torch.load(ckpt, weights_only=True)  # as written before `hitam.outside` existed
    del archive["payload"]["state"]["config"]["hitam"]["outside"]
    archive["sha256"] = content_hash(archive["payload"])
    torch.save(archive, ckpt)
    with pytest.raises(CheckpointError, match=r"another config \(changed: hitam.outside"):  # not its default
        resumed(scenario, tiny_config(hitam={"outside": "zero"}), ckpt)
    assert resumed(scenario, tiny_config(), ckpt) == reference[4:]


def test_save_load_round_trip_and_contract(scenario, tmp_path) -> None:
    model = RFLSCM.build(tiny_config(), GRID)
    fit(model, scenario, progress=False)
    path = model.save(tmp_path / "m.ckpt")
    loaded = load_model(path, scenario)
    assert isinstance(loaded, RFLSCM) and loaded.position == 7.0  # the last step begun: the trainer counts steps
    pairs, measured = scenario.rsrp_table(2, "ssb")
    cells, grids = pairs["cell_id"].to_numpy(), pairs["grid_id"].to_numpy()
    x = model.aps(cells, grids)
    assert x.shape == (len(pairs), GRID.num_bins) and bool((x >= 0).all())
    assert torch.equal(x, loaded.aps(cells, grids))
    assert int((x > 0).sum(1).max()) <= 3 * 9 * (1 + FILL_BLOCKS)  # zeros outside Ω′ (K_C β² bins) and the fill
    pred = loaded.predict_rsrp(scenario, 2, "ssb", pairs)
    assert pred.shape == measured.shape and np.isfinite(pred).all()
    with pytest.raises(UnsupportedError):
        model.aps(np.array([999]), grids[:1])
    with pytest.raises(UnsupportedError):
        model.aps(cells[:1], np.array([12345]))
    unseen = model.aps(cells[:1], np.array([12345]), grid_xyz=np.array([[30.0, 40.0, 1.5]]))
    assert unseen.shape == (1, GRID.num_bins)


def test_without_hitam_renders_every_visible_bin(scenario) -> None:
    model = RFLSCM.build(tiny_config(hitam={"enabled": False}, train={"steps": 3}, render={"min_gain_db": None}), GRID)
    summary = fit(model, scenario, progress=False)
    assert math.isfinite(summary["final_loss"]) and list(model.stages) == ["fine"]
    x = model.aps(np.array([11]), np.array([100]))
    assert int((x > 0).sum()) == GRID.num_bins
    model = RFLSCM.build(tiny_config(hitam={"enabled": False}, train={"steps": 1}, render={"min_gain_db": -10.0}), GRID)
    fit(model, scenario, progress=False)
    visible = model.scene.visible[0]
    assert 0 < visible.sum() < GRID.num_bins
    x = model.aps(np.array([11]), np.array([100]))[0].numpy()
    assert ((x > 0) == visible).all()


def test_only_the_directions_a_cell_sees_store_samples(scenario) -> None:
    """Issue 29: the renderer builds stored samples for the directions each cell sees and leaves the others empty;
    a seen ray's samples are those of the ray built alone."""
    from rflscm.render import build_ray_samples, gather_samples

    model = RFLSCM.build(tiny_config(train={"steps": 1}, render={"min_gain_db": -10.0}), GRID)
    fit(model, scenario, progress=False)
    renderer = model.renderer
    assert renderer is not None
    for kind in ("coarse", "fine"):
        rays = renderer.ray_samples(kind)
        visible = renderer.visible(kind)
        counts = (rays.samples.offsets[1:] - rays.samples.offsets[:-1]).view(visible.shape)
        assert bool((counts[~visible] == 0).all()) and bool((counts[visible] > 0).any()) and bool((~visible).any())
        xyz, _ = renderer.cells()
        cell, direction = torch.nonzero(visible)[-1].tolist()
        alone = build_ray_samples(
            xyz[cell], rays.directions[direction : direction + 1], model.scene.frame.num_samples, 8.0, model.prior
        )
        stored = gather_samples(rays.samples, torch.tensor([cell * visible.shape[1] + direction]))
        assert torch.equal(stored.index, alone.index.long()) and torch.equal(stored.phi, alone.phi)


def test_upsampling_during_training_survives_checkpoints(scenario, tmp_path) -> None:
    cfg = tiny_config(field={"voxel_m": 10.0, "init_voxel_m": 40.0, "upsample_at": [2, 5]})
    model = RFLSCM.build(cfg, GRID)
    fit(model, scenario, progress=False, checkpoint_path=tmp_path / "u.ckpt")
    fields = [m for m in model.stages.modules() if isinstance(m, TensorVM)]
    box = np.array(model.scene.frame.box_hi) - np.array(model.scene.frame.box_lo)
    assert all(f.resolution == tuple(int(round(e / 10.0)) + 1 for e in box) for f in fields)
    loaded = load_model(tmp_path / "u.ckpt")
    assert torch.equal(loaded.aps(np.array([11]), np.array([100])), model.aps(np.array([11]), np.array([100])))


def test_prior_needs_a_point_cloud(scenario) -> None:
    bare = dataclasses.replace(scenario, point_cloud=None)
    with pytest.raises(ConfigError, match="point cloud"):
        fit(RFLSCM.build(tiny_config(prior={"enabled": True}), GRID), bare, progress=False)


def test_coarse_model_is_frozen_once_alpha_is_one_and_its_selection_is_remembered(scenario) -> None:
    model = RFLSCM.build(tiny_config(train={"steps": 9}), GRID)
    snapshots = []
    fit(
        model,
        scenario,
        progress=False,
        callback=lambda m: snapshots.append([p.detach().clone() for p in model.stages["coarse"].parameters()]),
    )
    after_ramp = snapshots[6:]  # α = 1 from step 6 (warm-up 4, ramp 2)
    assert all(torch.equal(a, b) for snap in after_ramp[1:] for a, b in zip(after_ramp[0], snap))
    assert model._train.selection is not None
    d = model._train.data
    pairs = torch.arange(d.num_pairs)
    remembered = model._frozen_selection(pairs)
    fresh = model.renderer.expand(d.cell_index, model.renderer.coarse_power(d.cell_index, d.grid_xyz))
    assert torch.equal(remembered[1], fresh[1])
    assert torch.equal(remembered[0][fresh[1]], fresh[0][fresh[1]])


def test_the_coarse_fill_holds_the_next_blocks_coarse_power_outside_the_refined_ones(scenario) -> None:
    runs = {}
    for outside in ("zero", "coarse"):
        torch.manual_seed(0)
        runs[outside] = RFLSCM.build(tiny_config(train={"steps": 9}, hitam={"outside": outside}), GRID)
        fit(runs[outside], scenario, progress=False)
    model, hitam = runs["coarse"], runs["coarse"].hitam
    renderer, d = model.renderer, model._train.data
    cells, xyz = d.cell_index, d.grid_xyz
    with torch.no_grad():
        coarse = renderer.coarse_power(cells, xyz)
        bins, values = renderer.output(cells, xyz, model.position)
        zero_bins, zero_values = runs["zero"].renderer.output(cells, xyz, model.position)
    refined = hitam.top_k * hitam.beta**2
    assert bins.shape[1] == refined * (1 + FILL_BLOCKS) and zero_bins.shape[1] == refined
    assert torch.equal(bins[:, :refined], zero_bins) and torch.equal(values[:, :refined], zero_values)  # Ω′ as before
    parent = hitam.mapping.parent_of()
    chosen = renderer.expand(cells, coarse)
    for b in range(len(cells)):
        inside = set(parent[chosen[0][b][chosen[1][b]]].tolist())
        filled = parent[bins[b, refined:]][values[b, refined:] > 0]
        assert inside.isdisjoint(filled.tolist())  # the fill lies outside Ω′
        for block in filled.unique().tolist():  # a filled block holds at most its coarse power (the bins it sees)
            power = values[b, refined:][parent[bins[b, refined:]] == block].sum()
            assert float(power) <= float(coarse[b, block]) * (1 + 1e-5)
    assert float(values[:, refined:].sum()) > 0.0
    # training is the same; the pass after training and the predictions read the fill
    for name in ("coarse", "fine"):
        pairs_of_weights = zip(runs["zero"].stages[name].parameters(), model.stages[name].parameters())
        assert all(torch.equal(a, b) for a, b in pairs_of_weights)
    kept = {k: r.corrections.rendered for k, r in runs.items()}
    assert kept["zero"] is not None and kept["coarse"] is not None
    assert kept["zero"].bins.shape[1] == refined and kept["coarse"].bins.shape[1] == refined * (1 + FILL_BLOCKS)
    assert float(kept["coarse"].gains[:, refined:].sum()) > 0.0


def test_iterative_models_are_trained_by_the_trainer_not_by_model_fit(scenario) -> None:
    with pytest.raises(UnsupportedError, match="trained iteratively"):
        RFLSCM.build(tiny_config(), GRID).fit(scenario, progress=False)


def test_the_pairs_the_pass_corrected_are_answered_from_its_kept_renders_not_rendered_again(
    tmp_path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """After training every corrected pair's render is kept: ``aps`` answers those pairs without a render, the same
    (to float rounding) as rendering them again, through a save too; a pair asked at another position than its grid's
    is rendered there."""
    from rflscm.models.rflscm.renderer import APSRenderer

    scenario = load_scenario(tiny_scenario(tmp_path / "tiny", seed=0))
    model = RFLSCM.build(tiny_config(), AngleGrid.full_sphere(10, 12))
    fit(model, scenario, progress=False)
    kept = model.corrections.rendered
    assert kept is not None and len(kept.index) == model.corrections.corrected_pairs() > 0
    cells = kept.index.get_level_values(0).to_numpy()
    grids = kept.index.get_level_values(1).to_numpy()
    calls: list[int] = []
    output = APSRenderer.output

    def counted(self, c, g, position):  # type: ignore[no-untyped-def]
        calls.append(len(c))
        return output(self, c, g, position)

    monkeypatch.setattr(APSRenderer, "output", counted)
    stored = model.aps(cells, grids)
    assert calls == []
    xyz = scenario.grids.set_index("grid_id").loc[grids, ["x", "y", "z"]].to_numpy()
    assert torch.equal(model.aps(cells, grids, xyz), stored) and calls == []  # their own positions
    moved = model.aps(cells[:2], grids[:2], xyz[:2] + np.array([60.0, 40.0, 0.0]))
    assert sum(calls) == 2 and not torch.allclose(moved, stored[:2], rtol=1e-3, atol=0.0)
    loaded = load_model(model.save(tmp_path / "m.ckpt"), scenario)
    assert torch.equal(loaded.aps(cells, grids), stored)
    model.corrections.rendered = None  # the same pairs rendered again
    torch.testing.assert_close(model.aps(cells, grids), stored, rtol=1e-4, atol=1e-12)
