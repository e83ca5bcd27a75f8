"""Field models trained under a hold-out protocol are accepted by `rflscm evaluate` and `rflscm predict`
on the full scenario they were split from, in a fresh process (issue 11: the trainer used to overwrite
the full scenario's fingerprint, set by the protocol, with the training subset's)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.eval import make_protocol
from rflscm.eval.protocols import fit_with_protocol
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY

pytestmark = pytest.mark.slow
GRID = AngleGrid.full_sphere(10, 12)
TRAIN = {"steps": 4, "batch_pairs": 4, "pairs_per_cell": 2, "val_pairs": 2, "val_every": 2, "checkpoint_every": 2}
CONFIGS = {
    "rflscm": {
        "prior": {"enabled": False},
        "field": {"voxel_m": 20.0, "delta_rank": 2, "feature_rank": 2, "feature_dim": 4},
        "decoder": {"hidden": 8},
        "render": {"step_m": 8.0},
        "hitam": {"top_k": 3, "warmup_steps": 2, "ramp_steps": 1},
        "train": TRAIN,
    },
    "nerf2": {
        "prior": {"enabled": False},
        "field": {"hidden": 8, "layers": 2, "skip_at": 1, "pos_freqs": 2, "feature_dim": 4},
        "decoder": {"hidden": 8, "head_hidden": 4},
        "render": {"step_m": 8.0},
        "hitam": {"top_k": 3, "warmup_steps": 2, "ramp_steps": 1},
        "train": TRAIN,
    },
}
PROTOCOLS = {"unseen": {"fraction": 0.3}, "multifreq": {"train_percent": 30.0}}


def rflscm(*args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-m", "rflscm.cli", *args], capture_output=True, text=True, timeout=600, env=env
    )


@pytest.fixture(scope="module")
def scenario(tmp_path_factory: pytest.TempPathFactory):
    return load_scenario(tiny_scenario(tmp_path_factory.mktemp("protocol_ckpt"), seed=0))


@pytest.mark.parametrize("protocol", sorted(PROTOCOLS))
@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_field_model_trained_on_a_split_is_evaluated_on_the_full_scenario(
    scenario, tmp_path: Path, name: str, protocol: str
) -> None:
    proto = make_protocol(protocol, **PROTOCOLS[protocol])
    subset = proto.training_scenario(scenario)
    assert subset.fingerprint() != scenario.fingerprint()  # the split differs, so the bug would show
    model = MODEL_REGISTRY[name].build(CONFIGS[name], GRID, "cpu")
    ckpt = tmp_path / "m.ckpt"
    fit_with_protocol(model, scenario, proto, progress=False, checkpoint_path=ckpt)
    assert model.fingerprint == scenario.fingerprint()
    model.save(ckpt)

    run = rflscm("evaluate", str(ckpt), str(scenario.root), "--json", str(tmp_path / "m.json"), "--device", "cpu")
    assert run.returncode == 0, run.stderr
    metrics = json.loads((tmp_path / "m.json").read_text())
    assert metrics["protocol"]["name"] == protocol and metrics["model"]["name"] == name
    assert metrics["counts"]["ssb"]["scored_pairs"] > 0
    run = rflscm(
        "predict", str(ckpt), str(scenario.root), "--round", "1", "--out", str(tmp_path / "p.csv"), "--device", "cpu"
    )
    assert run.returncode == 0, run.stderr
    assert (tmp_path / "p.csv").stat().st_size > 0
