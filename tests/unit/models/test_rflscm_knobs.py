"""Every option of the RF-LSCM config does something: setting it away from its default changes a tiny
training run (its loss history, validation MAE or rendered APS), or, for the options that only bound
memory or I/O, leaves the results exactly as they were (issue 11: no dead knobs).  The options removed in
issue 11 are refused by name in a config, and load from a checkpoint only at the value now hard-wired."""

from __future__ import annotations

import dataclasses
import typing

import numpy as np
import pytest
import torch

from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.errors import CheckpointError, ConfigError
from rflscm.geometry import AngleGrid
from rflscm.models.rflscm import RFLSCM
from rflscm.models.rflscm.config import RFLSCMConfig, load_rflscm_config
from rflscm.train import fit

GRID = AngleGrid.full_sphere(10, 12)
BASE = {
    "prior": {"enabled": True},
    "field": {"voxel_m": 20.0, "delta_rank": 2, "feature_rank": 2, "feature_dim": 4},
    "decoder": {"hidden": 16},
    "render": {"step_m": 8.0},
    "hitam": {"beta": 2, "top_k": 3, "warmup_steps": 4, "ramp_steps": 2},
    "train": {"steps": 8, "batch_pairs": 4, "pairs_per_cell": 2, "val_pairs": 2, "val_every": 4, "checkpoint_every": 4},
}
# a value away from the tiny run's for every option (section, key, value)
CHANGES = [
    ("field", "voxel_m", 12.0),
    ("field", "delta_rank", 3),
    ("field", "feature_rank", 3),
    ("field", "feature_dim", 5),
    ("field", "building_loss_db", None),
    ("field", "upsample_at", (3,)),  # with init_voxel_m below
    ("decoder", "hidden", 12),
    ("decoder", "layers", 3),
    ("decoder", "inputs", "paper"),
    ("prior", "enabled", False),
    ("prior", "voxel_m", 4.0),
    ("render", "step_m", 6.0),
    ("render", "min_gain_db", None),
    ("hitam", "enabled", False),
    ("hitam", "beta", 3),
    ("hitam", "top_k", 1),
    ("hitam", "warmup_steps", 2),
    ("hitam", "ramp_steps", 4),
    ("hitam", "outside", "zero"),
    ("loss", "fidelity", "linear"),
    ("loss", "missing_penalty", 5.0),
    ("train", "steps", 6),
    ("train", "batch_pairs", 3),
    ("train", "pairs_per_cell", 1),
    ("train", "lr", {"tensors": 0.05, "networks": 0.001}),
    ("train", "lr_decay", 1.0),
    ("train", "val_pairs", 1),
    ("train", "val_every", 3),
    ("train", "seed", 1),
    ("corrections", "calibrate_levels", False),
    ("corrections", "pair_anchors", False),
    ("corrections", "pair_posterior", False),
    ("corrections", "wnomp_atoms", False),
    ("corrections", "lambda_groups", 1),
    ("corrections", "unseen_blend_grids", 0.3),
]
# options that bound memory or I/O only, or act only in a time-budget run (finish_share: its share of the budget, tested
# in test_rflscm_budget.py; wnomp_fallback: the pairs a budget's pass cannot reach, test_corrections.py): the same
# results in this step run, by design
NEUTRAL = [
    ("render", "chunk_samples", 64),
    ("train", "checkpoint_every", 1),
    ("train", "finish_share", 0.3),
    ("corrections", "wnomp_fallback", False),
]
EXTRA = {("field", "upsample_at"): {"init_voxel_m": 30.0}}

pytestmark = pytest.mark.usefixtures("one_thread")  # deterministic: a difference is the option's, not the threads'


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    return load_scenario(tiny_scenario(tmp_path_factory.mktemp("knobs"), seed=0))


def run(scenario, section: str | None = None, key: str | None = None, value=None) -> str:
    cfg = {k: dict(v) for k, v in BASE.items()}
    if section is not None:
        cfg.setdefault(section, {})[key] = value
        cfg[section].update(EXTRA.get((section, key), {}))
    torch.manual_seed(0)
    model = RFLSCM.build(cfg, GRID)
    history: list[tuple[float, float]] = []
    summary = fit(model, scenario, progress=False, callback=lambda m: history.append((m["total"], m["val_mae_db"])))
    aps = model.aps(np.array([11, 12]), np.array([100, 101])).double().sum(1).tolist()
    # the pair posterior's choice of λ on held-aside reports (it is applied only where it beats the field)
    fitted = model.corrections.posterior
    posterior = None if fitted is None else (sorted(fitted.scores.items()), sorted(fitted.atom_scores.items()))
    posterior = None if fitted is None else (*posterior, [sorted(g.items()) for g in fitted.groups])
    return repr((tuple(history), summary["val_mae_db"], tuple(aps), posterior))  # repr: NaN compares equal


@pytest.fixture(scope="module")
def reference(scenario) -> str:
    return run(scenario)


def test_every_option_is_listed_once() -> None:
    assert len(CHANGES) + len(NEUTRAL) + 1 == 40  # issue 11: at most 40
    listed = [(s, k) for s, k, _ in CHANGES + NEUTRAL] + [("field", "init_voxel_m")]  # with upsample_at
    sections = typing.get_type_hints(RFLSCMConfig)
    options = [(f.name, g.name) for f in dataclasses.fields(RFLSCMConfig) for g in dataclasses.fields(sections[f.name])]
    assert sorted(listed) == sorted(options) and len(set(listed)) == len(listed)


@pytest.mark.parametrize(("section", "key", "value"), CHANGES, ids=[f"{s}.{k}" for s, k, _ in CHANGES])
def test_option_changes_the_run(scenario, reference, section: str, key: str, value) -> None:
    assert run(scenario, section, key, value) != reference


def test_the_shape_fidelity_changes_the_run_too(scenario, reference) -> None:
    """``loss.fidelity`` has a third value (CHANGES lists one per option): each pair's level mostly profiled out."""
    assert run(scenario, "loss", "fidelity", "shape") not in (reference, run(scenario, "loss", "fidelity", "linear"))


@pytest.mark.parametrize(("section", "key", "value"), NEUTRAL, ids=[f"{s}.{k}" for s, k, _ in NEUTRAL])
def test_memory_and_io_options_leave_the_results_alone(scenario, reference, section: str, key: str, value) -> None:
    assert run(scenario, section, key, value) == reference


def test_init_voxel_m_sets_the_starting_resolution_of_an_upsampling_schedule(scenario) -> None:
    coarse = run(scenario, "field", "upsample_at", (3,))  # init_voxel_m 30 (EXTRA)
    EXTRA[("field", "upsample_at")] = {"init_voxel_m": 40.0}
    try:
        assert run(scenario, "field", "upsample_at", (3,)) != coarse
    finally:
        EXTRA[("field", "upsample_at")] = {"init_voxel_m": 30.0}


# --- options removed in issue 11 ------------------------------------------------------------------------------
OLD_DEFAULTS = {  # the 30 removed options at their defaults before issue 11 (written out, not read from the tables)
    "field": {
        "max_resolution": 256,
        "delta_basis": "per_channel",
        "feature_basis": "per_component",
        "init_scale": 0.1,
        "delta_init_scale": 0.2,
        "learn_mu": True,
        "init_loss_db": 0.01,
    },
    "decoder": {
        "dir_freqs": 6,
        "pos_freqs": 4,
        "grid_freqs": 6,
        "grid_features": True,
        "specular_powers": [1, 4, 16, 64],
        "specular_voxel_m": 4.0,
        "wavelength_freqs": 1,
        "output": "polar",
        "spreading_prior": True,
        "source_decay": 2.0,
        "init_radiance_db": -30.0,
        "init_level_db": -6.0,
    },
    "prior": {"radius_m": None, "density_threshold": None, "beta": None, "skip_below": 0.0},
    "render": {"num_samples": None, "inclusive": True, "max_log_gain": 0.0, "min_weight": 1e-5},
    "hitam": {"fine_init": "copy_coarse"},
    "loss": {"floor_db": -80.0},
    "train": {"val_beam_fraction": 0.25},
}
REMOVED = [(s, k) for s, keys in OLD_DEFAULTS.items() for k in keys]


def test_sixty_two_options_less_thirty_removed() -> None:
    assert len(REMOVED) == 30 and len(REMOVED) + 32 == 62
    sections = typing.get_type_hints(RFLSCMConfig)
    for section, key in REMOVED:
        assert key in sections[section].REMOVED and key not in {f.name for f in dataclasses.fields(sections[section])}


@pytest.mark.parametrize(("section", "key"), REMOVED, ids=[f"{s}.{k}" for s, k in REMOVED])
def test_a_removed_option_in_a_config_is_refused_as_removed(section: str, key: str) -> None:
    with pytest.raises(ConfigError, match=rf"^`{section}\.{key}` was removed \(issue 11: [^\n]*\); drop it\.$"):
        RFLSCM.build({section: {key: OLD_DEFAULTS[section][key]}}, GRID)


def test_a_removed_option_in_a_yaml_file_is_refused_in_one_line(tmp_path) -> None:
    path = tmp_path / "old.yaml"
    path.write_text("decoder:\n  hidden: 16\n  output: polar\n")
    with pytest.raises(ConfigError) as info:
        load_rflscm_config(path)
    assert str(info.value) == f"{path}: `decoder.output` was removed (issue 11: always polar); drop it."


def test_a_moved_correction_switch_in_the_train_section_names_its_new_section() -> None:
    with pytest.raises(ConfigError, match=r"^`train\.pair_anchors` was removed \(issue 24: moved to `corrections\."):
        RFLSCM.build({"train": {"pair_anchors": False}}, GRID)


def test_a_checkpoint_of_an_older_layout_is_refused_in_one_line(scenario, tmp_path) -> None:
    torch.manual_seed(0)
    model = RFLSCM.build({**BASE, "train": {**BASE["train"], "steps": 2}}, GRID)
    fit(model, scenario, progress=False)
    state = model.state_dict_for_checkpoint()
    assert RFLSCM.from_checkpoint(state).config == model.config
    old = {k: v for k, v in state.items() if k != "version"}  # the layout before issue 24 had no version
    old["config"] = {**state["config"], "decoder": {**state["config"]["decoder"], "output": "polar"}}
    for refused in (old, {**state, "version": 1}):
        with pytest.raises(CheckpointError, match=r"another version of rflscm .*retrain it") as info:
            RFLSCM.from_checkpoint(refused)
        assert "\n" not in str(info.value)
        with pytest.raises(CheckpointError, match=r"cannot resume: the checkpoint was written by another version"):
            model.resume_from({"model": "rflscm", "fingerprint": model.fingerprint, "state": refused}, tmp_path / "o")
