"""`rflscm train --minutes` and `rflscm demo --minutes`: a wall-clock training budget from the command line."""

from __future__ import annotations

from pathlib import Path

import pytest
from check_helpers import assert_one_line_error, run_cli

from rflscm.models import load_model

TINY = (
    "prior: {enabled: false}\nfield: {voxel_m: 20.0, delta_rank: 2, feature_rank: 2, feature_dim: 4}\n"
    "decoder: {hidden: 8}\nrender: {step_m: 8.0}\nhitam: {top_k: 2, warmup_steps: 4, ramp_steps: 2}\n"
    "train: {steps: 8, batch_pairs: 4, val_pairs: 2, val_every: 4}\n"
)


@pytest.mark.parametrize("minutes", ["0", "-1", "nan"])
def test_a_budget_that_is_not_positive_is_one_line_and_exit_2(
    scenario_dir: Path, tmp_path: Path, minutes: str, monkeypatch, capsys
) -> None:
    out_ckpt = tmp_path / "m.ckpt"
    code, out, err = run_cli(
        ["train", str(scenario_dir), "--minutes", minutes, "--out", str(out_ckpt)], monkeypatch, capsys
    )
    assert_one_line_error(code, out, err, ["--minutes must be a positive number of minutes", f"(got {minutes}"])
    assert not out_ckpt.exists()
    code, out, err = run_cli(["demo", "--minutes", minutes, "--out", str(tmp_path / "demo")], monkeypatch, capsys)
    assert_one_line_error(code, out, err, ["--minutes must be a positive number of minutes"])


def test_train_to_a_budget_records_it_and_resume_must_keep_it(
    scenario_dir: Path, tmp_path: Path, monkeypatch, capsys
) -> None:
    config, ckpt = tmp_path / "tiny.yaml", tmp_path / "m.ckpt"
    config.write_text(TINY)
    base = ["train", str(scenario_dir), "--config", str(config), "--out", str(ckpt), "--no-progress", "--device", "cpu"]
    code, _, err = run_cli([*base, "--minutes", "0.01"], monkeypatch, capsys)
    assert code == 0, err
    text = " ".join(err.split())
    assert "time budget: 0.01 min" in text and "of a 0.01-minute budget; the budget stopped it" in text
    train = load_model(ckpt).run_info["train"]
    assert train["budget_s"] == pytest.approx(0.6) and train["stopped_by_budget"] == 1.0 and train["steps"] >= 1
    assert train["train_time_s"] >= train["train_budget_s"]  # it trained to its share, whatever the step count
    # the share is the budget less the time kept for the pass after training, which the summary line reports
    assert train["train_budget_s"] < train["budget_s"] and train["total_s"] >= train["train_time_s"] + train["finish_s"]
    assert "the pass after training took" in text and "s in all" in text
    code, _, err = run_cli([*base, "--minutes", "0.02", "--resume"], monkeypatch, capsys)
    last = err.strip().splitlines()[-1]  # after the "training …" lines
    assert code == 2 and "Traceback" not in err and last.startswith("CheckpointError: "), err
    assert "a 0.6 s budget, this run asks for a 1.2 s budget; resume with --minutes 0.01" in last


def test_minutes_does_not_apply_to_wnomp(scenario_dir: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    ckpt = tmp_path / "w.ckpt"
    argv = ["train", str(scenario_dir), "--model", "wnomp", "--minutes", "1", "--out", str(ckpt), "--no-progress"]
    code, _, err = run_cli(argv, monkeypatch, capsys)
    assert code == 0, err
    assert "note: --minutes does not apply to wnomp" in " ".join(err.split()) and ckpt.is_file()
    assert "budget_s" not in (load_model(ckpt).run_info.get("fit") or {})


def test_the_demo_gives_rflscm_what_wnomp_left_and_at_least_a_floor() -> None:
    import io

    from rich.console import Console

    from rflscm.cli.demo import MIN_RFLSCM_S, rflscm_budget

    text = io.StringIO()
    console = Console(file=text, width=200)
    assert rflscm_budget(170.0, console) == 170.0 and text.getvalue() == ""
    assert rflscm_budget(-3.0, console) == MIN_RFLSCM_S
    assert "WNOMP left 0 s of the budget" in text.getvalue() and "will run over" in text.getvalue()


def test_a_demo_past_its_budget_says_where_the_time_went_and_what_budget_holds() -> None:
    from rflscm.cli.demo import OVER_NOTE, overrun_note

    parts = {"loading and WNOMP": 115.0, "RF-LSCM's fit": 70.0, "its evaluation and reports": 83.0}
    assert overrun_note(240.0, 240.0, parts) is None
    assert overrun_note((1 + OVER_NOTE) * 240.0 - 0.1, 240.0, parts) is None  # within a few percent: no note
    note = overrun_note(268.0, 240.0, parts)
    assert note is not None and "4.5 min of its 4-minute budget" in note
    assert "loading and WNOMP 115 s, RF-LSCM's fit 70 s, its evaluation and reports 83 s" in note
    assert "`--minutes 5`" in note  # 268 s and the 2 % it may run over fit 5 minutes


def test_the_demos_rflscm_answers_the_pairs_its_pass_misses_with_the_baselines_selected_settings(
    scenario_dir: Path, tmp_path: Path, monkeypatch, capsys
) -> None:
    """The demo hands RF-LSCM the WNOMP settings its baseline selected (``corrections.wnomp_fallback``), so that a
    pair the budget's pass does not reach is answered as the baseline answers it (that a user's ``--set`` of it still
    wins: ``tests/unit/test_config_overrides.py``)."""
    config = tmp_path / "tiny.yaml"
    config.write_text(TINY)
    base = ["demo", "--scenario", str(scenario_dir), "--config", str(config), "--minutes", "0.5", "--no-progress"]
    code, _, err = run_cli([*base, "--out", str(tmp_path / "a")], monkeypatch, capsys)
    assert code == 0, err
    wnomp = load_model(tmp_path / "a" / "wnomp.ckpt").config
    fallback = load_model(tmp_path / "a" / "rflscm.ckpt").config.corrections.wnomp_fallback
    assert fallback == wnomp  # the selected settings, whichever they are
