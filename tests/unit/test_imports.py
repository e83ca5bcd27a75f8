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


def test_train_does_not_import_the_models() -> None:
    # the models import the trainer, so the trainer must not need them at import time
    run = python("import sys, rflscm.train; print(sorted(m for m in sys.modules if m.startswith('rflscm.models')))")
    assert run.returncode == 0, run.stderr
    assert run.stdout.strip() == "[]"
