"""The global ``--threads N`` option (and ``$RFLSCM_THREADS``): torch's intra-op threads, set before any command.

Runs ``rflscm [--threads N] check TINY`` with typer's CliRunner (a cheap command on the tiny example);
the exit codes of a rejected value go through :func:`rflscm.cli.main`, the console-script entry point.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from rflscm.cli import _register_commands, app, main
from rflscm.data.examples import tiny_scenario
from rflscm.errors import ConfigError

runner = CliRunner()


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    _register_commands()
    return tiny_scenario(tmp_path_factory.mktemp("threads") / "tiny", seed=5)


@pytest.fixture(autouse=True)
def two_threads(monkeypatch: pytest.MonkeyPatch):
    """Start each test from 2 threads and no $RFLSCM_THREADS; restore torch's setting afterwards."""
    before = torch.get_num_threads()
    monkeypatch.delenv("RFLSCM_THREADS", raising=False)
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def test_threads_1_is_accepted_and_sets_torch_threads(tiny: Path) -> None:
    result = runner.invoke(app, ["--threads", "1", "check", str(tiny)])
    assert result.exit_code == 0, result.output
    assert torch.get_num_threads() == 1


def test_environment_variable_is_the_default_and_the_option_wins(tiny: Path) -> None:
    result = runner.invoke(app, ["check", str(tiny)])
    assert result.exit_code == 0, result.output
    assert torch.get_num_threads() == 2  # neither given: torch's setting is left alone
    result = runner.invoke(app, ["check", str(tiny)], env={"RFLSCM_THREADS": "1"})
    assert result.exit_code == 0, result.output
    assert torch.get_num_threads() == 1
    torch.set_num_threads(2)
    result = runner.invoke(app, ["--threads", "1", "check", str(tiny)], env={"RFLSCM_THREADS": "2"})
    assert result.exit_code == 0, result.output
    assert torch.get_num_threads() == 1


def test_threads_0_is_a_config_error(tiny: Path) -> None:
    result = runner.invoke(app, ["--threads", "0", "check", str(tiny)])
    assert result.exit_code != 0
    assert isinstance(result.exception, ConfigError)
    assert "--threads must be at least 1" in str(result.exception) and "got 0" in str(result.exception)
    assert torch.get_num_threads() == 2


@pytest.mark.parametrize(
    ("args", "env", "message"),
    [
        (["--threads", "0"], None, "ConfigError: --threads must be at least 1 CPU thread (got 0)."),
        (["--threads", "-3"], None, "ConfigError: --threads must be at least 1 CPU thread (got -3)."),
        ([], "0", "ConfigError: the environment variable RFLSCM_THREADS must be at least 1 CPU thread (got 0)."),
        ([], "two", "ConfigError: the environment variable RFLSCM_THREADS must be a whole number"),
        (["--threads", "x"], None, "Invalid value for '--threads'"),
    ],
)
def test_rejected_values_exit_2_with_one_clear_message(
    tiny: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    args: list[str],
    env: str | None,
    message: str,
) -> None:
    if env is not None:
        monkeypatch.setenv("RFLSCM_THREADS", env)
    monkeypatch.setattr(sys, "argv", ["rflscm", *args, "check", str(tiny)])
    with pytest.raises(SystemExit) as exit_info:
        main()
    err = capsys.readouterr().err
    assert exit_info.value.code == 2
    assert message in err and "Traceback" not in err
    assert torch.get_num_threads() == 2
