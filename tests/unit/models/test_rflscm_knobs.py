"""Every option of the RF-LSCM config does something: setting it away from its default changes a tiny
training run (its loss history, validation MAE or rendered APS), or, for the options that only bound
memory or I/O, leaves the results exactly as they were (issue 11: no dead knobs)."""

from __future__ import annotations

import dataclasses
import typing

import numpy as np
import pytest
import torch

from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.geometry import AngleGrid
from rflscm.models.rflscm import RFLSCM
from rflscm.models.rflscm_config import RFLSCMConfig
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
    ("field", "max_resolution", 3),
    ("field", "delta_rank", 3),
    ("field", "feature_rank", 3),
    ("field", "feature_dim", 5),
    ("field", "delta_basis", "per_mode"),
    ("field", "feature_basis", "per_channel"),
    ("field", "init_scale", 0.3),
    ("field", "delta_init_scale", 0.5),
    ("field", "learn_mu", False),
    ("field", "init_loss_db", 0.1),
    ("field", "building_loss_db", None),
    ("field", "upsample_at", (3,)),  # with init_voxel_m below
    ("decoder", "hidden", 12),
    ("decoder", "layers", 3),
    ("decoder", "inputs", "paper"),
    ("decoder", "dir_freqs", 2),
    ("decoder", "pos_freqs", 2),
    ("decoder", "grid_freqs", 2),
    ("decoder", "grid_features", False),
    ("decoder", "specular_powers", (1,)),
    ("decoder", "specular_voxel_m", 8.0),
    ("decoder", "wavelength_freqs", 2),
    ("decoder", "output", "cartesian"),
    ("decoder", "spreading_prior", False),
    ("decoder", "source_decay", 0.0),
    ("decoder", "init_radiance_db", -10.0),
    ("decoder", "init_level_db", None),
    ("prior", "enabled", False),
    ("prior", "voxel_m", 4.0),
    ("prior", "radius_m", 2.0),
    ("prior", "density_threshold", 1.0),
    ("prior", "beta", 0.5),
    ("prior", "skip_below", 0.05),
    ("render", "step_m", 6.0),
    ("render", "num_samples", 2),
    ("render", "inclusive", False),
    ("render", "max_log_gain", -1.0),
    ("render", "min_gain_db", None),
    ("render", "min_weight", 0.05),
    ("hitam", "enabled", False),
    ("hitam", "beta", 3),
    ("hitam", "top_k", 1),
    ("hitam", "warmup_steps", 2),
    ("hitam", "ramp_steps", 4),
    ("hitam", "fine_init", "fresh"),
    ("loss", "fidelity", "linear"),
    ("loss", "sparsity", 0.5),
    ("loss", "missing_penalty", 5.0),
    ("loss", "floor_db", -10.0),
    ("train", "steps", 6),
    ("train", "batch_pairs", 3),
    ("train", "pairs_per_cell", 1),
    ("train", "lr", {"tensors": 0.05, "networks": 0.001}),
    ("train", "lr_decay", 1.0),
    ("train", "val_pairs", 1),
    ("train", "val_beam_fraction", 0.6),
    ("train", "val_every", 3),
    ("train", "seed", 1),
]
# options that bound memory or I/O only: the same results, by design
NEUTRAL = [("render", "chunk_samples", 64), ("train", "checkpoint_every", 1)]
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
    return repr((tuple(history), summary["val_mae_db"], tuple(aps)))  # repr: NaN (no validation yet) compares equal


@pytest.fixture(scope="module")
def reference(scenario) -> str:
    return run(scenario)


def test_every_option_is_listed_once() -> None:
    assert len(CHANGES) + len(NEUTRAL) + 1 == 62
    listed = [(s, k) for s, k, _ in CHANGES + NEUTRAL] + [("field", "init_voxel_m")]  # tested with upsample_at
    sections = typing.get_type_hints(RFLSCMConfig)
    options = [(f.name, g.name) for f in dataclasses.fields(RFLSCMConfig) for g in dataclasses.fields(sections[f.name])]
    assert sorted(listed) == sorted(options) and len(set(listed)) == len(listed)


@pytest.mark.parametrize(("section", "key", "value"), CHANGES, ids=[f"{s}.{k}" for s, k, _ in CHANGES])
def test_option_changes_the_run(scenario, reference, section: str, key: str, value) -> None:
    assert run(scenario, section, key, value) != reference


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
