"""`rflscm simulate` end to end (procedural backend, tiny) and its user-facing errors."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow


def rflscm(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "rflscm.cli", *args], capture_output=True, text=True, timeout=300)


def rflscm_in_process(monkeypatch, capsys, *args: str) -> tuple[int, str]:
    """Run ``rflscm ARGS`` through :func:`rflscm.cli.main` in this process: (exit code, stderr)."""
    from rflscm.cli import main

    monkeypatch.setattr(sys, "argv", ["rflscm", *args])
    with pytest.raises(SystemExit) as exit_info:
        main()
    return int(exit_info.value.code), capsys.readouterr().err


def test_simulate_then_check(tmp_path: Path) -> None:
    config = tmp_path / "sim.yaml"
    config.write_text(
        "site_radius_m: 100\npoint_cloud_points_per_m2: 0.05\n"
        "angle_grid: {num_el: 31, num_az: 36, el_min_deg: -90, el_step_deg: 6}\n"
        "backend_options: {size_m: 220, num_buildings: 10}\n"
    )
    out = tmp_path / "sc"
    run = rflscm(
        "simulate",
        "--backend",
        "procedural",
        "--scene",
        "city",
        "--sites",
        "2",
        "--grids",
        "30",
        "--carriers",
        "3.5e9,2.1e9",
        "--seed",
        "3",
        "--config",
        str(config),
        "--out",
        str(out),
        "--device",
        "cpu",
    )
    assert run.returncode == 0, run.stderr
    assert "tracing" in run.stderr and "wrote" in run.stderr
    check = rflscm("check", str(out))
    assert check.returncode == 0, check.stderr
    assert "12 on 2 site(s)" in check.stdout and "grids: 30" in check.stdout
    assert (out / "truth" / "aps.parquet").is_file()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".sc.")]  # temporary folder removed

    again = rflscm("simulate", "--sites", "1", "--grids", "10", "--out", str(out))
    assert again.returncode == 2 and "not empty" in again.stderr and "--force" in again.stderr
    field = tmp_path / "field"
    field_config = tmp_path / "field.yaml"
    field_config.write_text("field_model: {samples_per_grid: 8, csi_top_n: 2}\n")
    remeasured = rflscm(
        "simulate",
        "--from-trace",
        str(out),
        "--measurements",
        "field",
        "--config",
        str(field_config),
        "--out",
        str(field),
    )
    assert remeasured.returncode == 0, remeasured.stderr
    check = rflscm("check", str(field))
    assert check.returncode == 0, check.stderr
    assert "reported fraction" in check.stdout and "'top_n': 2" in check.stdout and "sinr" in check.stdout
    moved = rflscm("simulate", "--from-trace", str(out), "--grids", "5", "--out", str(tmp_path / "f2"))
    assert moved.returncode == 2 and "--grids cannot change it" in moved.stderr

    forced = rflscm(
        "simulate",
        "--sites",
        "1",
        "--grids",
        "10",
        "--carriers",
        "3.5e9",
        "--config",
        str(config),
        "--out",
        str(out),
        "--force",
        "--no-progress",
    )
    assert forced.returncode == 0, forced.stderr
    assert "3 on 1 site(s)" in rflscm("check", str(out)).stdout


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--backend", "raytracer9000"], "'raytracer9000' is not one of 'procedural', 'sionna'"),
        (["--scene", "atlantis"], "valid: city"),
        (["--carriers", "3500,2100"], "looks like MHz"),
        (["--carriers", "3.5,2.1"], "looks like GHz"),
    ],
)
def test_user_mistakes_exit_2_with_one_line(tmp_path: Path, monkeypatch, capsys, args, message) -> None:
    code, err = rflscm_in_process(monkeypatch, capsys, "simulate", "--out", str(tmp_path / "x"), *args)
    assert code == 2
    assert message in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


def test_force_refuses_to_delete_a_folder_that_is_not_a_scenario(tmp_path: Path, monkeypatch, capsys) -> None:
    (tmp_path / "keep.txt").write_text("precious")
    code, err = rflscm_in_process(monkeypatch, capsys, "simulate", "--out", str(tmp_path), "--force")
    assert code == 2 and "no scenario.yaml" in err
    assert (tmp_path / "keep.txt").read_text() == "precious"


def test_missing_sionna_extra_says_how_to_install(tmp_path: Path, monkeypatch, capsys) -> None:
    import importlib.util

    real_find_spec = importlib.util.find_spec

    def no_sionna(name, *args):
        return None if name == "sionna" else real_find_spec(name, *args)

    monkeypatch.setattr(importlib.util, "find_spec", no_sionna)
    code, err = rflscm_in_process(monkeypatch, capsys, "simulate", "--backend", "sionna", "--out", str(tmp_path / "x"))
    assert code == 2 and "pip install -e .[rt]" in err
