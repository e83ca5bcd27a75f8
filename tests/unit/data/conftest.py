"""Fixtures for the data tests: the tiny scenario (built once, copied per test)."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

import pandas as pd
import pytest
import yaml

from rflscm.data import Scenario, load_scenario, read_table, write_table
from rflscm.data.examples import tiny_scenario


@pytest.fixture(scope="session")
def _tiny_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tiny_scenario(tmp_path_factory.mktemp("tiny_template") / "tiny", seed=3)


@pytest.fixture
def tiny_dir(_tiny_template: Path, tmp_path: Path) -> Path:
    """A fresh, writable copy of the tiny CSV scenario folder."""
    return Path(shutil.copytree(_tiny_template, tmp_path / "tiny"))


@pytest.fixture
def tiny(tiny_dir: Path) -> Scenario:
    return load_scenario(tiny_dir)


def _edit_table(path: Path, change: Callable[[pd.DataFrame], pd.DataFrame | None]) -> None:
    """Read a table, let ``change`` modify it (in place or by returning a new one), write it back."""
    df = read_table(path)
    out = change(df)
    write_table(df if out is None else out, path)


def _edit_yaml(root: Path, change: Callable[[dict], None]) -> None:
    """Load scenario.yaml of ``root``, let ``change`` modify the mapping in place, write it back."""
    path = root / "scenario.yaml"
    data = yaml.safe_load(path.read_text())
    change(data)
    path.write_text(yaml.safe_dump(data, sort_keys=False))


@pytest.fixture
def edit_table() -> Callable[..., None]:
    """``edit_table(path, change)``: modify a table file in place."""
    return _edit_table


@pytest.fixture
def edit_yaml() -> Callable[..., None]:
    """``edit_yaml(root, change)``: modify a scenario's scenario.yaml in place."""
    return _edit_yaml
