"""Issue 25, deliverable 4 through the CLI: `train --set` changes the checkpoint's config; a wrong key is one line."""

from __future__ import annotations

from pathlib import Path

from check_helpers import assert_one_line_error, run_cli

from rflscm.models import load_model


def test_train_set_reaches_the_checkpoint_and_a_wrong_key_is_one_line(
    scenario_dir: Path, tmp_path: Path, monkeypatch, capsys
) -> None:
    ckpt = tmp_path / "w.ckpt"
    base = ["train", str(scenario_dir), "--model", "wnomp", "--out", str(ckpt), "--device", "cpu", "--no-progress"]
    code, _, err = run_cli([*base, "--set", "k_max=3", "--set", "residual_floor=0.05"], monkeypatch, capsys)
    assert code == 0, err
    model = load_model(ckpt)
    assert model.config.k_max == 3 and model.config.residual_floor == 0.05
    assert model.run_info["config_overrides"] == {"preset": None, "set": ["k_max=3", "residual_floor=0.05"]}
    ckpt.unlink()
    code, out, err = run_cli([*base, "--set", "kmax=3"], monkeypatch, capsys)
    assert_one_line_error(code, out, err, ["--set kmax=3: unknown key `kmax` in the top level; valid keys:", "k_max"])
    assert not ckpt.exists()
    code, out, err = run_cli([*base, "--preset", "fast"], monkeypatch, capsys)
    assert_one_line_error(code, out, err, ["--preset 'fast' is not a preset; choose one of: quick, full."])
