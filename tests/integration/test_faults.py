"""Fault injection (issue 27): signals, full disks, concurrent writers, outputs that are inputs, hostile
YAML, paths and Parquet, planted code in a checkpoint.  Every case ends in one line and a non-zero exit,
the previous output intact and no temporary file left.  Tiny configs: the whole file runs in well under a
minute on one core."""

from __future__ import annotations

import builtins
import errno
import os
import resource
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from rflscm.cli import main
from rflscm.config import parse_yaml
from rflscm.data import load_scenario
from rflscm.data.io import read_table, write_table
from rflscm.data.safe_io import atomic_write, discard_stale_temps
from rflscm.errors import CheckpointError, ConfigError, DataError, RflscmError
from rflscm.models.base import read_checkpoint

SRC = str(Path(__file__).resolve().parents[2] / "src")
CONFIG = {
    "prior": {"enabled": False},
    "field": {"voxel_m": 20.0, "delta_rank": 2, "feature_rank": 2, "feature_dim": 4},
    "decoder": {"hidden": 16},
    "render": {"step_m": 8.0},
    "hitam": {"top_k": 3, "warmup_steps": 4, "ramp_steps": 2},
    "train": {
        "steps": 40,
        "batch_pairs": 4,
        "pairs_per_cell": 2,
        "val_pairs": 2,
        "val_every": 4,
        "checkpoint_every": 2,
    },
}
SLOW_CHILD = textwrap.dedent(
    """
    import sys, time
    import rflscm.train as train

    step = train.Trainer.train_step

    def slow_step(self):  # room for a signal to land in the middle of training
        time.sleep(0.05)
        return step(self)

    train.Trainer.train_step = slow_step
    from rflscm.cli import main

    sys.argv = ["rflscm", *sys.argv[1:]]
    main()
    """
)


def env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": SRC + os.pathsep + os.environ.get("PYTHONPATH", ""), "OMP_NUM_THREADS": "1"}


def cli(*args: str, capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """The CLI in this process; (exit code, stderr, stdout)."""
    argv, threads = sys.argv, torch.get_num_threads()
    sys.argv = ["rflscm", "--threads", "1", *args]
    code = 0
    try:
        main()
    except SystemExit as exc:
        code = int(exc.code or 0)
    finally:
        sys.argv = argv
        torch.set_num_threads(threads)
    captured = capsys.readouterr()
    return code, captured.err, captured.out


def one_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines and "Traceback" not in err, err
    return lines[-1]


def no_temps(folder: Path) -> None:
    assert not [p for p in folder.rglob("*.tmp") if p.is_file()], list(folder.rglob("*.tmp"))


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory, template: Path) -> tuple[Path, Path]:
    """(scenario folder, a WNOMP checkpoint of it)."""
    root = tmp_path_factory.mktemp("faults")
    scenario = Path(shutil.copytree(template, root / "tiny"))
    ckpt = root / "w.ckpt"
    argv = sys.argv
    sys.argv = [
        "rflscm",
        "--threads",
        "1",
        "train",
        str(scenario),
        "--model",
        "wnomp",
        "--out",
        str(ckpt),
        "--no-progress",
    ]
    try:
        main()
    except SystemExit as exc:
        assert not exc.code
    finally:
        sys.argv = argv
    return scenario, ckpt


# --- signals ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_during_train_fails_in_one_line_and_resume_finishes(scenario_dir, tmp_path, signum, code) -> None:
    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(CONFIG))
    out = tmp_path / "run.ckpt"
    args = ["--threads", "1", "train", str(scenario_dir), "--config", str(config), "--out", str(out), "--no-progress"]
    child = subprocess.Popen([sys.executable, "-c", SLOW_CHILD, *args], env=env(), stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not out.is_file() and time.monotonic() < deadline and child.poll() is None:
        time.sleep(0.05)
    assert out.is_file(), "no checkpoint was saved"
    child.send_signal(signum)
    _, err = child.communicate(timeout=120)
    assert child.returncode == code, err
    line = one_line(err)
    assert line.startswith(f"Interrupted: {signal.Signals(signum).name}") and "--resume" in line and str(out) in line
    payload = read_checkpoint(out)
    assert payload["run_info"]["interrupted"] is True
    assert 0 < payload["train_state"]["step"] < 40
    no_temps(tmp_path)

    resumed = subprocess.run(
        [sys.executable, "-m", "rflscm.cli", *args, "--resume"], env=env(), capture_output=True, text=True, timeout=300
    )
    assert resumed.returncode == 0, resumed.stderr
    payload = read_checkpoint(out)
    assert payload["train_state"]["step"] == 40 and "interrupted" not in payload["run_info"]


def test_evaluate_says_a_checkpoint_was_interrupted(trained, tmp_path, capsys) -> None:
    scenario, ckpt = trained
    from rflscm.models import load_model

    model = load_model(ckpt, load_scenario(scenario))
    model.run_info["interrupted"] = True
    half = model.save(tmp_path / "half.ckpt")
    code, err, out = cli("evaluate", str(half), str(scenario), "--no-oracle", capsys=capsys)
    assert code == 0, err
    printed = " ".join(out.split())  # rich wraps long lines
    assert "was interrupted" in printed and "--resume" in printed
    code, err, out = cli("evaluate", str(ckpt), str(scenario), "--no-oracle", capsys=capsys)
    assert code == 0 and "interrupted" not in out, err


def test_sigint_is_not_exit_0_for_any_command(monkeypatch, capsys) -> None:
    """The handler main() installs turns SIGINT into exit 130 with one line, whatever the command."""
    import rflscm.cli as cli_module

    def interrupted(*_args, **_kwargs):
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(1)  # the handler raises before this ends

    monkeypatch.setattr(type(cli_module.app), "__call__", lambda self, **kw: interrupted())
    before = signal.getsignal(signal.SIGINT)  # Python's default; SIG_IGN where a shell started the run in background
    code, err, _ = cli("check", "nowhere", capsys=capsys)
    assert code == 130 and one_line(err).startswith("Interrupted: SIGINT")
    assert signal.getsignal(signal.SIGINT) is before  # restored after main()


# --- outputs never destroy inputs ---------------------------------------------------------------------


def test_outputs_that_are_inputs_are_refused_before_any_work(trained, tmp_path, capsys) -> None:
    scenario, ckpt = trained
    measurements = scenario / "measurements.parquet"
    if not measurements.exists():
        measurements = next(scenario.glob("measurements.*"))
    before = {p: p.read_bytes() for p in (measurements, ckpt, scenario / "scenario.yaml")}
    link = tmp_path / "alias.parquet"
    link.symlink_to(measurements)
    hard = tmp_path / "hard.ckpt"
    os.link(ckpt, hard)
    hard_json = tmp_path / "hard.json"  # the checkpoint under another name (a hard link)
    os.link(ckpt, hard_json)
    cases = [
        ("predict", str(ckpt), str(scenario), "--out", str(measurements), "--force"),
        ("predict", str(ckpt), str(scenario), "--out", str(link), "--force"),
        ("predict", str(ckpt), str(scenario), "--out", str(tmp_path / "p.parquet"), "--kpi-json", str(hard_json)),
        ("train", str(scenario), "--model", "wnomp", "--out", str(scenario / "scenario.yaml"), "--force"),
        ("evaluate", str(hard), str(scenario), "--json", str(hard_json), "--force"),
    ]
    for args in cases:
        code, err, _ = cli(*args, capsys=capsys)
        assert code == 2 and "an input of this command" in one_line(err), (args, err)
    assert all(p.read_bytes() == data for p, data in before.items())
    assert not (tmp_path / "p.parquet").exists()


def test_replacing_an_output_needs_force_and_formats_are_checked_first(trained, tmp_path, capsys) -> None:
    scenario, ckpt = trained
    other = tmp_path / "other.ckpt"
    other.write_bytes(ckpt.read_bytes())
    code, err, _ = cli("train", str(scenario), "--model", "wnomp", "--out", str(other), capsys=capsys)
    assert code == 2 and "exists already; add --force" in one_line(err)
    assert other.read_bytes() == ckpt.read_bytes()
    for args, message in [
        (("--out", str(tmp_path / "p.txt")), "unknown table format"),
        (("--out", "/proc/rflscm-x.parquet"), "cannot take a new file"),
        (("--kpi-json", str(tmp_path)), "must end in .json"),
        (("--kpi-json", str(tmp_path / "k.json"), "--threshold", "nan"), "--threshold must be a finite number"),
        (("--seed", str(10**20)), "--seed must be between"),
    ]:
        code, err, _ = cli("predict", str(ckpt), str(scenario), *args, capsys=capsys)
        assert code == 2 and message in one_line(err), (args, err)
    (tmp_path / "k.json").mkdir()
    code, err, _ = cli(
        "predict",
        str(ckpt),
        str(scenario),
        "--out",
        str(tmp_path / "p.parquet"),
        "--kpi-json",
        str(tmp_path / "k.json"),
        capsys=capsys,
    )
    assert code == 2 and "is a folder" in one_line(err) and not (tmp_path / "p.parquet").exists()


def test_a_legacy_tmp_folder_does_not_break_a_save(trained, tmp_path, capsys) -> None:
    scenario, _ = trained
    out = tmp_path / "w.ckpt"
    (tmp_path / "w.ckpt.tmp").mkdir()
    code, err, _ = cli("train", str(scenario), "--model", "wnomp", "--out", str(out), "--no-progress", capsys=capsys)
    assert code == 0, err
    assert read_checkpoint(out)["model"] == "wnomp"


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--tilt-range", "0:15:1e-9"), "above the limit of 100,000"),
        (("--tilt-range", "nan:nan"), "must be finite"),
        (("--azimuth-range", "0:inf"), "-60…60 degrees"),
        (("--time-budget", "-1"), "--time-budget must be between 0"),
        (("--threshold", "nan"), "--threshold must be a finite number"),
        (("--aps-cache", "cache.pkl"), "must end in .pt"),
        (("--out", __file__), "is a file; give a folder"),
    ],
)
def test_optimize_values_are_checked_before_work(trained, tmp_path, capsys, args, message) -> None:
    scenario, ckpt = trained
    code, err, _ = cli("optimize", str(ckpt), str(scenario), "--out", str(tmp_path / "o"), *args, capsys=capsys)
    assert code == 2 and message in one_line(err), err
    assert not (tmp_path / "o").exists()


# --- faults while writing -----------------------------------------------------------------------------


def _limit_file_size() -> None:
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG instead of killing
    resource.setrlimit(resource.RLIMIT_FSIZE, (1_000, 1_000))


def test_file_too_large_ends_in_one_line_with_the_previous_output_intact(trained, tmp_path) -> None:
    scenario, ckpt = trained
    out = tmp_path / "p.csv"  # 96 predicted beams: a few kB, past the 1 kB limit
    write_table(pd.DataFrame({"a": [1.0]}), out)
    before = out.read_bytes()
    args = ["--threads", "1", "predict", str(ckpt), str(scenario), "--out", str(out), "--pairs", "measured", "--force"]
    run = subprocess.run(
        [sys.executable, "-m", "rflscm.cli", *args],
        env=env(),
        capture_output=True,
        text=True,
        timeout=300,
        preexec_fn=_limit_file_size,
    )
    assert run.returncode == 2, run.stderr
    line = one_line(run.stderr)
    assert "File too large" in line and "the previous file is kept" in line
    assert out.read_bytes() == before
    no_temps(tmp_path)


def test_disk_full_removes_the_temporary_file(tmp_path) -> None:
    out = tmp_path / "t.csv"
    out.write_text("a\n1\n")

    def full(tmp: Path) -> None:
        tmp.write_text("a\n2\n")
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with pytest.raises(DataError, match=r"No space left on device.*previous file is kept"):
        atomic_write(out, full)
    assert out.read_text() == "a\n1\n"
    no_temps(tmp_path)


def test_a_signal_inside_a_write_leaves_no_temporary_file(tmp_path) -> None:
    out = tmp_path / "t.csv"

    def interrupted(tmp: Path) -> None:
        tmp.write_text("half")
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        atomic_write(out, interrupted)
    assert not out.exists()
    no_temps(tmp_path)


WRITER = textwrap.dedent(
    """
    import sys
    import numpy as np, pandas as pd
    from rflscm.data.io import write_table

    value = float(sys.argv[2])
    for _ in range(15):
        write_table(pd.DataFrame({"v": np.full(200_000, value)}), sys.argv[1])
    """
)


def test_two_concurrent_writers_both_complete_whole(tmp_path) -> None:
    out = tmp_path / "shared.parquet"
    writers = [
        subprocess.Popen([sys.executable, "-c", WRITER, str(out), str(v)], env=env(), stderr=subprocess.PIPE, text=True)
        for v in (1.0, 2.0)
    ]
    for w in writers:
        _, err = w.communicate(timeout=120)
        assert w.returncode == 0, err
    values = read_table(out)["v"].to_numpy()
    assert len(values) == 200_000 and np.unique(values).size == 1 and values[0] in (1.0, 2.0)
    no_temps(tmp_path)


def test_stale_temporaries_of_dead_writers_go_but_a_live_writers_stay(tmp_path) -> None:
    out = tmp_path / "run.ckpt"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = tmp_path / f".run.ckpt.{int(dead.stdout)}.abc.tmp"
    live = tmp_path / f".run.ckpt.{os.getppid()}.abc.tmp"
    legacy = tmp_path / "run.ckpt.tmp"
    for p in (stale, live, legacy):
        p.write_bytes(b"x")
    assert set(discard_stale_temps(out)) == {stale, legacy}
    assert live.exists()


# --- hostile inputs -----------------------------------------------------------------------------------


def _yaml(scenario: Path) -> dict:
    return yaml.safe_load((scenario / "scenario.yaml").read_text())


def _write_yaml(scenario: Path, data: dict) -> None:
    (scenario / "scenario.yaml").write_text(yaml.safe_dump(data, sort_keys=False))


def test_paths_outside_the_scenario_are_refused_unless_allowed(scenario_dir, tmp_path) -> None:
    data = _yaml(scenario_dir)
    grids = scenario_dir / data["grids"]
    moved = tmp_path / ("elsewhere" + grids.suffix)
    shutil.copy(grids, moved)
    for name in (str(moved), f"../{moved.name}", "/etc/passwd"):
        _write_yaml(scenario_dir, {**data, "grids": name})
        with pytest.raises(DataError, match="resolves outside the scenario folder"):
            load_scenario(scenario_dir)
    (scenario_dir / "link.csv").symlink_to(moved)
    _write_yaml(scenario_dir, {**data, "grids": "link.csv"})
    with pytest.raises(DataError, match="resolves outside the scenario folder"):
        load_scenario(scenario_dir)
    _write_yaml(scenario_dir, {**data, "grids": str(moved), "allow_outside": True})
    assert len(load_scenario(scenario_dir).grids)
    _write_yaml(scenario_dir, {**data, "truth": "/etc"})
    with pytest.raises(DataError, match="resolves outside"):
        load_scenario(scenario_dir)


def test_special_files_are_refused_without_blocking(scenario_dir) -> None:
    data = _yaml(scenario_dir)
    fifo = scenario_dir / "fifo.parquet"
    os.mkfifo(fifo)
    zero = scenario_dir / "zero.csv"
    zero.symlink_to("/dev/zero")
    _write_yaml(scenario_dir, {**data, "grids": zero.name})
    with pytest.raises(DataError, match="resolves outside the scenario folder"):
        load_scenario(scenario_dir)
    for name in (fifo.name, zero.name):  # allowed outside, still never opened
        _write_yaml(scenario_dir, {**data, "grids": name, "allow_outside": True})
        with pytest.raises(DataError, match="not a regular file"):
            load_scenario(scenario_dir)


def test_size_limits_are_checked_before_reading(scenario_dir, monkeypatch) -> None:
    monkeypatch.setenv("RFLSCM_MAX_FILE_BYTES", "100")
    with pytest.raises(ConfigError, match="above the 100-byte limit"):
        load_scenario(scenario_dir)


def test_billion_laughs_is_one_line_and_merge_keys_work(scenario_dir) -> None:
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 9)]
    with pytest.raises(ConfigError, match="expands to more than 1,000,000 values"):
        parse_yaml("\n".join(lines))
    text = (scenario_dir / "scenario.yaml").read_text()
    (scenario_dir / "scenario.yaml").write_text(text + "simulation:\n" + "".join(f"  {line}\n" for line in lines))
    with pytest.raises(ConfigError, match="expands to more than"):
        load_scenario(scenario_dir)
    assert parse_yaml("base: &b {type: ssb, tilts_deg: [0]}\nssb8:\n  <<: *b\n  tilts_deg: [3]\n")["ssb8"] == {
        "type": "ssb",
        "tilts_deg": [3],
    }


def test_declared_beams_and_grid_heights_are_bounded(scenario_dir) -> None:
    data = _yaml(scenario_dir)
    huge = {"type": "ssb", "azimuths_deg": [0.0] * 3000, "tilts_deg": [0.0, 1.0]}
    _write_yaml(scenario_dir, {**data, "codebooks": {**data["codebooks"], "huge": huge}})
    with pytest.raises(ConfigError, match="6,000 beams, above the 4,096-beam limit"):
        load_scenario(scenario_dir)
    _write_yaml(scenario_dir, data)
    grids_path = scenario_dir / data["grids"]
    grids = read_table(grids_path)
    grids.loc[0, "z"] = 1500.0
    write_table(grids, grids_path)
    with pytest.raises(DataError, match="more than the 500 m a ground UE can be"):
        load_scenario(scenario_dir)
    _write_yaml(scenario_dir, {**data, "ue": "aerial"})
    assert load_scenario(scenario_dir).grids["z"].max() == 1500.0


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(offset=st.integers(min_value=0, max_value=10_000), flips=st.binary(min_size=1, max_size=8))
def test_damaged_parquet_is_an_error_or_the_same_table_never_a_crash(tmp_path, offset, flips) -> None:
    path = tmp_path / "t.parquet"
    table = pd.DataFrame({"a": np.arange(500, dtype=np.float64), "b": np.arange(500, dtype=np.int64)})
    write_table(table, path)
    data = bytearray(path.read_bytes())
    at = offset % len(data)
    for i, b in enumerate(flips):
        data[(at + i) % len(data)] ^= b or 1
    bad = tmp_path / "bad.parquet"
    bad.write_bytes(bytes(data))
    try:
        read = read_table(bad)
    except RflscmError as exc:
        assert "\n" not in str(exc)
    else:  # a flip in padding or unused metadata: the data itself must be intact (page checksums)
        pd.testing.assert_frame_equal(read.reset_index(drop=True), table, check_dtype=False)


class _Payload:
    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return (builtins.open, (str(self.marker), "w"))


def test_a_planted_pickle_payload_in_a_checkpoint_never_runs(tmp_path) -> None:
    marker = tmp_path / "pwned"
    for name, obj in (("header.ckpt", _Payload(marker)), ("inside.ckpt", {"format": 1, "payload": _Payload(marker)})):
        torch.save(obj, tmp_path / name)
        with pytest.raises(CheckpointError):
            read_checkpoint(tmp_path / name)
        assert not marker.exists()


def test_check_lists_every_file_it_read(scenario_dir, capsys) -> None:
    code, err, out = cli("check", str(scenario_dir), capsys=capsys)
    assert code == 0, err
    listed = " ".join(out.split()).split("files read: ", 1)[1]
    data = _yaml(scenario_dir)
    for name in ("scenario.yaml", data["grids"], data["measurements"], *(r["cells"] for r in data["rounds"].values())):
        assert os.path.realpath(scenario_dir / name) in listed, name


@pytest.mark.parametrize("delay", [0.3, 1.2, 1.8])
def test_sigterm_during_predict_leaves_the_previous_output_whole(trained, tmp_path, delay) -> None:
    scenario, ckpt = trained
    out = tmp_path / "p.csv"
    write_table(pd.DataFrame({"a": [1.0]}), out)
    before = out.read_bytes()
    args = ["--threads", "1", "predict", str(ckpt), str(scenario), "--out", str(out), "--force", "--kpi"]
    child = subprocess.Popen([sys.executable, "-m", "rflscm.cli", *args], env=env(), stderr=subprocess.PIPE, text=True)
    time.sleep(delay)
    child.send_signal(signal.SIGTERM)
    _, err = child.communicate(timeout=120)
    # -15: the signal landed before main() installed its handler (still importing) or after it returned
    assert child.returncode in (0, 143, -signal.SIGTERM), err
    if child.returncode == 143:
        assert one_line(err).startswith("Interrupted: SIGTERM")
    data = out.read_bytes()
    assert data == before or len(read_table(out)) > 1  # the old file or the whole new one, never a part
    no_temps(tmp_path)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(offset=st.integers(min_value=0, max_value=1 << 20), flips=st.binary(min_size=1, max_size=4))
def test_a_damaged_checkpoint_is_one_line_or_loads_the_same(trained, tmp_path, offset, flips) -> None:
    _, ckpt = trained
    data = bytearray(ckpt.read_bytes())
    at = offset % len(data)
    for i, b in enumerate(flips):
        data[(at + i) % len(data)] ^= b or 1
    bad = tmp_path / "bad.ckpt"
    bad.write_bytes(bytes(data))
    try:
        payload = read_checkpoint(bad)
    except RflscmError as exc:
        assert "\n" not in str(exc)
    else:  # a flip the zip container ignores: the content hash vouches for the payload
        assert payload["model"] == "wnomp"


def test_a_stride_0_tensor_is_refused_before_it_is_expanded(tmp_path) -> None:
    huge = torch.zeros(1).expand(1 << 30)  # 4 GiB as a float32 shape, 4 bytes in the file
    torch.save(
        {"format": "rflscm-checkpoint/2", "sha256": "x", "payload": {"model": "wnomp", "state": {"w": huge}}},
        tmp_path / "s.ckpt",
    )
    with pytest.raises(CheckpointError, match="refused before expanding it") as exc:
        read_checkpoint(tmp_path / "s.ckpt")
    assert "\n" not in str(exc.value)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("--carriers", "nan"), "not a carrier frequency"),
        (("--carriers", "3.5e9,inf"), "not a carrier frequency"),
        (("--seed", "-5"), "--seed must be between 0 and 9223372036854775807"),
        (("--raw-fading", "nan"), "--raw-fading"),
    ],
)
def test_simulate_values_are_checked_before_work(tmp_path, capsys, args, message) -> None:
    code, err, _ = cli("simulate", "--out", str(tmp_path / "s"), *args, capsys=capsys)
    assert code == 2 and message in one_line(err), err
    assert not (tmp_path / "s").exists()
