"""`rflscm simulate --workers 2` (traces and the ideal regime's RSRP on a local 2-CPU Ray) writes the scenario that
one worker writes, byte for byte, for a new trace and for --from-trace."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("ray")
pytestmark = pytest.mark.slow


def rflscm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "rflscm.cli", "--threads", "1", *args], capture_output=True, text=True, timeout=300
    )


def files(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("how", ["trace", "from-trace"])
def test_simulate_on_two_ray_workers_writes_the_serial_scenario_byte_for_byte(tmp_path: Path, how: str) -> None:
    base = ["simulate", "--sites", "3", "--grids", "40", "--seed", "11", "--no-progress"]
    if how == "from-trace":
        made = rflscm(*base, "--out", str(tmp_path / "source"))
        assert made.returncode == 0, made.stderr
        base = ["simulate", "--from-trace", str(tmp_path / "source"), "--seed", "5", "--measurements", "ideal"]
    written = {}
    for workers in ("1", "2"):
        out = tmp_path / f"w{workers}"
        run = rflscm(*base, "--out", str(out), "--workers", workers)
        assert run.returncode == 0, run.stderr
        written[workers] = files(out)
    if how == "trace":
        assert "on 2 Ray workers" in " ".join(run.stderr.split())
    serial, parallel = written["1"], written["2"]
    assert {"measurements.parquet", "truth/paths.parquet", "truth/rsrp_noiseless.parquet"} <= set(serial)
    assert list(parallel) == list(serial)
    assert [name for name in serial if parallel[name] != serial[name]] == []
