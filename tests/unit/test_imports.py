"""Every public package imports on its own in a fresh interpreter (no circular imports).

In one pytest process the packages are already imported in some order, which hides a cycle that only
bites when a given package is imported first; hence one subprocess per package.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

ENV = {**os.environ, "OMP_NUM_THREADS": "1"}


def python(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, env=ENV)


@pytest.mark.parametrize("module", ["rflscm.train", "rflscm.eval", "rflscm.bench", "rflscm.sim.truth", "rflscm.cli"])
def test_package_imports_first_in_a_fresh_interpreter(module: str) -> None:
    run = python(f"import {module}")
    assert run.returncode == 0, run.stderr


def test_models_cannot_reach_the_simulator_or_its_truth() -> None:
    # the oracle is an evaluation device (rflscm.eval.oracle): importing the models loads nothing of rflscm.sim
    run = python("import rflscm.models, sys; assert not [m for m in sys.modules if m.startswith('rflscm.sim')]")
    assert run.returncode == 0, run.stderr


def test_models_do_not_import_the_trainer() -> None:
    # layering: the trainer drives the models, never the reverse
    run = python("import sys, rflscm.models; print(sorted(m for m in sys.modules if m.startswith('rflscm.train')))")
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]"
