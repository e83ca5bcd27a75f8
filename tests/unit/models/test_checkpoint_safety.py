"""Issue 14, items 4-7 and 13: checkpoints are safe to open, checked, and every model refuses bad input.

Each test is built from a case that once went wrong: a pickle that runs code, flipped bytes that changed
predictions by 11 dB, NaN weights written as NaN predictions, corrupted bin indices, a WNOMP fit on no
round-1 reports, a resume with another `train.steps`, a 0-byte `.tmp` left behind by kill -9.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch
from tiny_rflscm import tiny_config

from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.data.pointcloud import PointCloud
from rflscm.errors import CheckpointError, DataError
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY, load_model
from rflscm.models.base import NonFiniteError, content_hash, from_plain, read_checkpoint, to_plain
from rflscm.models.rflscm import RFLSCM
from rflscm.models.rflscm.config import RFLSCMConfig, from_dict
from rflscm.models.rflscm.scene import check_scene_box
from rflscm.train import fit

SMALL = AngleGrid.full_sphere(10, 12)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory):
    return load_scenario(tiny_scenario(tmp_path_factory.mktemp("ckpt") / "tiny", seed=1))


@pytest.fixture(scope="module")
def wnomp(tiny):
    model = MODEL_REGISTRY["wnomp"].build({"k_max": 3}, SMALL, "cpu")
    model.fingerprint = tiny.fingerprint()
    fit(model, tiny, progress=False)
    return model


class _RunsCode:
    """A pickle payload that would create a file when unpickled (what `weights_only=False` allowed)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def test_pickle_with_code_payload_is_refused_unrun(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    path = tmp_path / "evil.ckpt"
    torch.save({"format": "rflscm-checkpoint/2", "payload": _RunsCode(marker)}, path)
    with pytest.raises(CheckpointError, match="refused: the file holds Python objects"):
        load_model(path)
    assert not marker.exists()


def test_flipped_bytes_are_refused_or_change_nothing(wnomp, tiny, tmp_path: Path) -> None:
    path = wnomp.save(tmp_path / "w.ckpt")
    data = path.read_bytes()
    cells, grids = wnomp.cell_ids, wnomp.grid_ids
    expected = wnomp.aps(cells, grids)
    refused = 0
    for k, offset in enumerate(np.linspace(0, len(data) - 1, 40).astype(int)):
        damaged = bytearray(data)
        damaged[offset] ^= 0x5A
        bad = tmp_path / f"flip{k}.ckpt"
        bad.write_bytes(bytes(damaged))
        try:
            loaded = load_model(bad, tiny)
        except CheckpointError as exc:
            assert "\n" not in str(exc)
            refused += 1
            continue
        assert torch.equal(loaded.aps(cells, grids), expected), offset  # a flip in padding changes nothing
    assert refused >= 15  # the rest fell into the zip's alignment padding


def test_flipped_weight_bytes_fail_the_hash(wnomp, tmp_path: Path) -> None:
    """A flip inside the tensor data keeps the zip readable: only the SHA-256 catches it."""
    path = wnomp.save(tmp_path / "w.ckpt")
    data = bytearray(path.read_bytes())
    values = wnomp.values.numpy().tobytes()
    at = bytes(data).find(values[:16])
    assert at > 0
    data[at + 5] ^= 0x01
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="does not match the SHA-256"):
        read_checkpoint(path)


def test_nan_weights_are_refused_at_load_and_at_prediction(tiny, tmp_path: Path) -> None:
    model = RFLSCM.build(tiny_config(train={"steps": 2}), SMALL)
    fit(model, tiny, progress=False)
    with torch.no_grad():
        for p in model.stages.parameters():
            p.fill_(float("nan"))  # the model keeps no rendered APS (issue 11), so its answers change at once
    path = model.save(tmp_path / "nan.ckpt")
    with pytest.raises(CheckpointError, match=r"non-finite values \(NaN or inf\) in `stages\."):
        load_model(path, tiny)
    pairs, _ = tiny.rsrp_table(1, "ssb")
    fitted = model.aps

    def nan_for_one_pair(cells, grids, xyz=None):
        x = fitted(cells, grids, xyz).clone()
        x[-1, 3] = float("nan")
        return x

    model.aps = nan_for_one_pair  # whatever the cause, a non-finite answer never reaches an output file
    with pytest.raises(NonFiniteError, match=r"non-finite or negative APS for \(cell 11, grid 102\) \(1 of"):
        model.predict_rsrp(tiny, 2, "ssb", pairs)


def test_corrupted_bin_indices_are_refused(wnomp, tiny, tmp_path: Path) -> None:
    saved = wnomp.indices.clone()
    try:
        wnomp.indices[0, 0] = 10**6
        path = wnomp.save(tmp_path / "idx.ckpt")  # a consistent file (valid hash) with a bad index
    finally:
        wnomp.indices = saved
    with pytest.raises(CheckpointError, match=r"bin index \(1000000\) lies outside the angle grid's 0…119"):
        load_model(path, tiny)


def test_old_format_folder_and_garbage_are_one_line_errors(tmp_path: Path) -> None:
    old = tmp_path / "old.ckpt"
    torch.save({"format": "rflscm-checkpoint/1", "state": {}}, old)
    with pytest.raises(CheckpointError, match="older rflscm"):
        read_checkpoint(old)
    (tmp_path / "dir.ckpt").mkdir()
    with pytest.raises(CheckpointError, match="is a folder"):
        read_checkpoint(tmp_path / "dir.ckpt")
    (tmp_path / "text.ckpt").write_text("hello")
    with pytest.raises(CheckpointError, match=r"not an rflscm checkpoint|not a readable rflscm checkpoint"):
        read_checkpoint(tmp_path / "text.ckpt")
    (tmp_path / "empty.ckpt").write_bytes(b"")
    with pytest.raises(CheckpointError, match=r"not an rflscm checkpoint|not a readable rflscm checkpoint"):
        read_checkpoint(tmp_path / "empty.ckpt")


def test_plain_payload_round_trip() -> None:
    value = {"a": np.arange(3), "b": (1, 2.5, "x"), "c": np.float32(1.5), "d": {3: torch.ones(2)}, "e": Path("p")}
    plain = to_plain(value)
    back = from_plain(plain)
    assert np.array_equal(back["a"], np.arange(3)) and back["b"] == [1, 2.5, "x"] and back["c"] == 1.5
    assert torch.equal(back["d"][3], torch.ones(2)) and back["e"] == "p"
    before = content_hash(plain)
    assert before == content_hash(to_plain(value))
    plain["d"][3][0] = 2.0
    assert content_hash(plain) != before


def test_wnomp_refuses_zero_round1_reports(tiny) -> None:
    m = tiny.measurements.copy()
    m.loc[m["round"] == 1, "rsrp_dbm"] = np.nan
    empty = tiny.with_measurements(m, validate=False)
    for name in ("wnomp", "rflscm"):
        config = None if name == "wnomp" else tiny_config()
        with pytest.raises(DataError, match=r"no reported round-1 RSRP|no reported RSRP in round 1"):
            fit(MODEL_REGISTRY[name].build(config, SMALL, "cpu"), empty, progress=False)


def test_resume_refuses_other_steps_and_other_models(tiny, wnomp, tmp_path: Path) -> None:
    ckpt = tmp_path / "run.ckpt"
    fit(RFLSCM.build(tiny_config(train={"steps": 4}), SMALL), tiny, progress=False, checkpoint_path=ckpt)
    with pytest.raises(CheckpointError, match=r"trained towards `train.steps` = 4, this run asks for 8"):
        fit(RFLSCM.build(tiny_config(), SMALL), tiny, progress=False, checkpoint_path=ckpt, resume=True)
    other = wnomp.save(tmp_path / "w.ckpt")
    with pytest.raises(CheckpointError, match="holds a 'wnomp' model, not 'rflscm'"):
        fit(RFLSCM.build(tiny_config(), SMALL), tiny, progress=False, checkpoint_path=other, resume=True)


def test_stale_partial_save_is_removed(tiny, tmp_path: Path) -> None:
    ckpt = tmp_path / "run.ckpt"
    tmp = tmp_path / "run.ckpt.tmp"
    tmp.write_bytes(b"")  # what kill -9 during a save leaves
    fit(RFLSCM.build(tiny_config(train={"steps": 4}), SMALL), tiny, progress=False, checkpoint_path=ckpt)
    assert ckpt.is_file() and not tmp.exists()
    tmp.write_bytes(b"")  # resuming a finished run saves nothing more, and still cleans up
    fit(RFLSCM.build(tiny_config(train={"steps": 4}), SMALL), tiny, progress=False, checkpoint_path=ckpt, resume=True)
    assert not tmp.exists()


def test_scene_box_too_large_to_voxelise_is_refused(tiny) -> None:
    cfg = from_dict(RFLSCMConfig, tiny_config(prior={"enabled": True, "voxel_m": 2.0}))
    with pytest.raises(DataError, match=r"the scene box is 5e\+06 × 2000 × 50 m: at `model.prior.voxel_m` = 2 m"):
        check_scene_box(cfg, np.array([0.0, 0.0, 0.0]), np.array([5e6, 2e3, 50.0]))
    with pytest.raises(DataError, match="not finite"):
        check_scene_box(cfg, np.array([0.0, 0.0, 0.0]), np.array([np.inf, 2e3, 50.0]))
    far = load_scenario(tiny.root)
    far.point_cloud = PointCloud(far.point_cloud.xyz + np.array([4e6, 0.0, 0.0]), far.point_cloud.classification)
    with pytest.raises(DataError, match="voxels, more than the 1e\\+08 a model can hold"):
        fit(RFLSCM.build(tiny_config(prior={"enabled": True}), SMALL), far, progress=False)
