"""NeRF²-LSCM: presets, the shared trunk, gradients, learning on a tiny scenario, checkpoints."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from rflscm.config import to_dict
from rflscm.errors import ConfigError
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY, load_model
from rflscm.models.nerf2 import NeRF2Config, NeRF2Field, NeRF2FieldConfig, NeRF2LSCM
from rflscm.models.rflscm import RFLSCM
from rflscm.models.rflscm.fields import SceneFrame
from rflscm.train import fit

GRID = AngleGrid(num_el=16, num_az=18, el_min_deg=-90.0, el_step_deg=12.0)
NARROW = {
    "field": {"hidden": 16, "layers": 4, "skip_at": 2, "pos_freqs": 4, "feature_dim": 8},
    "decoder": {"hidden": 16, "head_hidden": 8},
    "train": {"steps": 40, "batch_pairs": 8, "val_pairs": 4, "val_every": 20, "lr": {"networks": 0.01}},
}

pytestmark = pytest.mark.usefixtures("one_thread")


@pytest.fixture(scope="module")
def scenario(tmp_path_factory: pytest.TempPathFactory):
    from rflscm.data import load_scenario
    from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario

    cfg = SimulationConfig(
        name="nerf2-tiny",
        num_sites=1,
        max_grids=16,
        seed=3,
        site_radius_m=60.0,
        carriers_hz=(3.5e9,),
        sector_azimuths_deg=(0.0, 180.0),
        point_cloud_points_per_m2=0.05,
        angle_grid=GRID,
    )
    out = tmp_path_factory.mktemp("nerf2") / "scen"
    build_scenario(ProceduralCity(seed=2, size_m=160.0, num_buildings=6), cfg, out, progress=False)
    return load_scenario(out)


def narrow(**over: dict) -> dict:
    cfg = {k: dict(v) for k, v in NARROW.items()}
    for key, value in over.items():
        cfg[key] = {**cfg.get(key, {}), **value}
    return cfg


def test_registered_and_presets_have_the_paper_sizes() -> None:
    assert MODEL_REGISTRY["nerf2"] is NeRF2LSCM
    full = NeRF2LSCM.build("full", GRID).config
    assert (full.field.layers, full.field.hidden, full.field.skip_at, full.field.pos_freqs) == (8, 256, 4, 10)
    assert (full.decoder.hidden, full.decoder.head_hidden, full.decoder.layers) == (256, 128, 2)
    assert full.train.lr == {"networks": 0.001}
    quick = NeRF2LSCM.build("quick", GRID).config
    assert quick.field.layers == 8 and quick.field.skip_at == 4 and quick.field.pos_freqs == 10
    assert quick.field.hidden < full.field.hidden  # shrunk for CPU (said so in the YAML)
    # RF-LSCM's other sections are shared: same loss, renderer, HiTAM keys and defaults
    assert to_dict(NeRF2Config().loss) == to_dict(MODEL_REGISTRY["rflscm"].build(None, GRID).config.loss)


def test_shared_physics_defaults_follow_rflscm() -> None:
    from rflscm.models.rflscm.config import FieldConfig

    ours, theirs = NeRF2FieldConfig(), FieldConfig()
    assert ours.building_loss_db == theirs.building_loss_db  # same medium, same start: only the fields differ
    for key in ("learn_mu", "init_loss_db"):  # fixed since issue 11, for both models alike
        assert NeRF2FieldConfig.REMOVED[key] == FieldConfig.REMOVED[key], key


def test_config_errors_are_clear() -> None:
    with pytest.raises(ConfigError, match="skip_at"):
        NeRF2LSCM.build({"field": {"layers": 4, "skip_at": 4}}, GRID)
    with pytest.raises(ConfigError, match="unknown key"):
        NeRF2LSCM.build({"field": {"delta_rank": 4}}, GRID)


def _frame() -> SceneFrame:
    return SceneFrame((-50.0, -50.0, 0.0), (50.0, 50.0, 30.0), 16, 0.1, 40.0)


def test_field_shapes_skip_and_free_space_start() -> None:
    torch.manual_seed(0)
    cfg = NeRF2Config().field
    net = NeRF2Field(cfg, _frame(), delta_channels=3)
    # NeRF²: 8 layers, the 63-wide encoding re-enters at layer 4
    widths = [layer.in_features for layer in net.trunk.hidden]
    assert widths == [63, 256, 256, 256, 256 + 63, 256, 256, 256]
    pts = torch.rand(500, 3) * 100.0 - 50.0
    code = net.encode(pts)
    raw = net.delta(code)
    assert raw.shape == (500, 3) and raw.abs().max() < 1.0  # raw ≈ 0: the medium starts ≈ free space
    assert net.features(code[:10]).shape == (10, 256)
    assert net.delta_module() is net  # the attenuation initialisation fits the whole trunk


def test_nerf2_is_rflscm_with_mlp_fields_plugged_in_at_construction(scenario) -> None:
    model = NeRF2LSCM.build(narrow(hitam={"warmup_steps": 2, "ramp_steps": 2, "top_k": 4, "beta": 2}), GRID)
    model._prepare(scenario)
    for stage in model.stages.values():
        assert isinstance(stage.fields, NeRF2Field)
        # the radiance head is built narrow (NeRF²: 256 → 128 → 2), not patched after construction
        assert [layer.out_features for layer in stage.decoder.mlp.hidden] == [8]
        assert stage.decoder.mlp.hidden[0].in_features == 16
    for method in ("training_losses", "aps", "prepare", "parameter_groups", "on_step_begin"):
        assert getattr(NeRF2LSCM, method) is getattr(RFLSCM, method), method  # nothing but the fields differs


def test_gradient_reaches_every_parameter(scenario) -> None:
    torch.manual_seed(0)
    for hitam in ({"enabled": False}, {"warmup_steps": 2, "ramp_steps": 4, "top_k": 4, "beta": 2}):
        model = NeRF2LSCM.build(narrow(hitam=hitam), GRID)
        model._prepare(scenario)
        step = 3 if hitam.get("enabled", True) else 0  # mid-ramp: both the coarse and the refinement model learn
        model.on_step_begin(step, float(step))
        pairs = torch.arange(min(8, model._train.data.num_pairs))
        model.training_losses(pairs, step)["total"].backward()
        names = [n for n, p in model.stages.named_parameters() if p.grad is None or not bool(p.grad.abs().sum() > 0)]
        assert not names, f"no gradient reaches {names} (hitam={hitam})"
        assert set(model.parameter_groups()) == {"networks"}
        assert sum(p.numel() for p in model.parameter_groups()["networks"]) == sum(
            p.numel() for p in model.stages.parameters()
        )


def test_tiny_scenario_loss_decreases(scenario) -> None:
    torch.manual_seed(0)
    model = NeRF2LSCM.build(narrow(hitam={"enabled": False}, train={"steps": 80}), GRID)
    model._prepare(scenario)
    pairs = torch.nonzero(model._train.data.beam_mask.any(1)).squeeze(1)
    with torch.no_grad():
        before = float(model.training_losses(pairs, 0)["total"])
    summary = fit(model, scenario, progress=False)
    with torch.no_grad():
        after = float(model.training_losses(pairs, model.position + 1)["total"])
    assert summary["steps"] == 80 and np.isfinite(after)
    assert after < 0.9 * before, (before, after)


def test_save_load_round_trip(scenario, tmp_path: Path) -> None:
    torch.manual_seed(0)
    cfg = narrow(hitam={"warmup_steps": 3, "ramp_steps": 2, "top_k": 4, "beta": 2}, train={"steps": 8})
    model = NeRF2LSCM.build(cfg, GRID)
    fit(model, scenario, progress=False)
    path = model.save(tmp_path / "m.ckpt")
    loaded = load_model(path, scenario)
    assert isinstance(loaded, NeRF2LSCM) and loaded.position == model.position == 7.0
    assert to_dict(loaded.config) == to_dict(model.config)
    cells = scenario.cell_ids()[[0, -1]]
    grids = scenario.grid_ids()[:2]
    a, b = model.aps(cells, grids), loaded.aps(cells, grids)
    assert a.shape == (2, GRID.num_bins) and bool(a.sum() > 0)
    torch.testing.assert_close(a, b)
