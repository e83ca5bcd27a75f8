"""Fixtures for the evaluation tests."""

from __future__ import annotations

import pytest
from eval_helpers import simulate

from rflscm.data import load_scenario


@pytest.fixture(scope="session")
def sim_scenario(tmp_path_factory: pytest.TempPathFactory):
    """A 2-site, 2-carrier procedural scenario with ground truth (built once per session)."""
    return load_scenario(simulate(tmp_path_factory.mktemp("eval_sim") / "sc"))
