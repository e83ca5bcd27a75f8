"""Shared helpers of the `rflscm check` tests: the CLI run and table edits (fixtures: conftest.py)."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import pandas as pd
import pytest

from rflscm.cli import main
from rflscm.data import read_table, write_table


def run_check(path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """Run ``rflscm check PATH`` through the console-script entry point; returns (exit code, stdout, stderr)."""
    return run_cli(["check", str(path)], monkeypatch, capsys)


def run_cli(
    argv: list[str], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> tuple[int, str, str]:
    """Run ``rflscm ARGV…`` through the console-script entry point; returns (exit code, stdout, stderr)."""
    monkeypatch.setattr(sys, "argv", ["rflscm", *argv])
    code: int | str | None = 0
    try:
        main()
    except SystemExit as exc:
        code = exc.code
    out, err = capsys.readouterr()
    return (0 if code is None else int(code)), out, err


def table(name: str, change: Callable[[pd.DataFrame], pd.DataFrame | None]) -> Callable[[Path], None]:
    """A mutation of a scenario folder: ``change`` edits table ``name`` in place or returns a new one."""

    def apply(root: Path) -> None:
        df = read_table(root / name)
        out = change(df)
        write_table(df if out is None else out, root / name)

    return apply


def assert_one_line_error(code: int, out: str, err: str, expected: list[str]) -> None:
    """Exit 2, no traceback, exactly one `DataError:`/`ConfigError:` line on stderr holding every ``expected`` text."""
    assert code == 2, (out, err)
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(("DataError: ", "ConfigError: ")), lines[0]
    for text in expected:
        assert text in lines[0], lines[0]
