"""Fixtures of the integration tests: a fresh copy of a tiny scenario folder per test."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from rflscm.data.examples import tiny_scenario


@pytest.fixture(scope="module")
def template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tiny_scenario(tmp_path_factory.mktemp("check") / "tiny", seed=5)


@pytest.fixture
def scenario_dir(template: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(template, tmp_path / "tiny"))
