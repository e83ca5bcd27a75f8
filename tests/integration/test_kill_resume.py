"""kill -9 during a checkpoint save, then ``rflscm train --resume``: the same weights as a run never killed.

The child process is the real CLI; its ``torch.save`` is wrapped so that at the third save it writes half
of the checkpoint into the temporary file and then sends itself SIGKILL — a kill at the worst moment,
made deterministic.  The resumed run must start from the last complete checkpoint, remove the partial
temporary file and end with weights bit-identical to an uninterrupted run (issue 14, item 13).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import torch
import yaml

from rflscm.cli import main
from rflscm.data.examples import tiny_scenario
from rflscm.models.base import read_checkpoint

CONFIG = {
    "prior": {"enabled": False},
    "field": {"voxel_m": 20.0, "delta_rank": 2, "feature_rank": 2, "feature_dim": 4},
    "decoder": {"hidden": 16},
    "render": {"step_m": 8.0},
    "hitam": {"top_k": 3, "warmup_steps": 4, "ramp_steps": 2},
    "train": {"steps": 8, "batch_pairs": 4, "pairs_per_cell": 2, "val_pairs": 2, "val_every": 4, "checkpoint_every": 2},
}

CHILD = textwrap.dedent(
    """
    import io, os, signal, sys
    import torch

    real_save, calls = torch.save, [0]

    def dying_save(obj, f, *args, **kwargs):
        calls[0] += 1
        if calls[0] == int(os.environ["KILL_AT_SAVE"]):
            buf = io.BytesIO()
            real_save(obj, buf, *args, **kwargs)
            f.write(buf.getvalue()[: len(buf.getvalue()) // 2])
            f.flush()
            os.kill(os.getpid(), signal.SIGKILL)
        return real_save(obj, f, *args, **kwargs)

    torch.save = dying_save
    from rflscm.cli import main

    sys.argv = ["rflscm", *sys.argv[1:]]
    main()
    """
)


def arguments(scenario: Path, config: Path, out: Path, *extra: str) -> list[str]:
    return [
        "--threads",
        "1",
        "train",
        str(scenario),
        "--config",
        str(config),
        "--out",
        str(out),
        "--no-progress",
        *extra,
    ]


def train_killed(scenario: Path, config: Path, out: Path, kill_at: int) -> subprocess.CompletedProcess:
    """The CLI in a child process that SIGKILLs itself inside save number ``kill_at``."""
    env = {**os.environ, "KILL_AT_SAVE": str(kill_at), "OMP_NUM_THREADS": "1"}
    src = str(Path(__file__).resolve().parents[2] / "src")
    env["PYTHONPATH"] = src + os.pathsep + env.get("PYTHONPATH", "")
    command = [sys.executable, "-c", CHILD, *arguments(scenario, config, out)]
    return subprocess.run(command, capture_output=True, text=True, timeout=300, env=env)


def train(scenario: Path, config: Path, out: Path, *extra: str) -> int:
    """The CLI in this process (the same code path as the console script); returns the exit code."""
    argv, threads = sys.argv, torch.get_num_threads()
    sys.argv = ["rflscm", *arguments(scenario, config, out, *extra)]
    try:
        main()
    except SystemExit as exc:
        return int(exc.code or 0)
    finally:
        sys.argv = argv
        torch.set_num_threads(threads)
    return 0


def test_kill_during_save_then_resume_gives_identical_weights(tmp_path: Path) -> None:
    scenario = tiny_scenario(tmp_path / "tiny", seed=0)
    config = tmp_path / "tiny.yaml"
    config.write_text(yaml.safe_dump(CONFIG))
    assert train(scenario, config, tmp_path / "reference.ckpt") == 0

    run = tmp_path / "run.ckpt"
    killed = train_killed(scenario, config, run, kill_at=3)  # saves at steps 2, 4, then killed inside the one at 6
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    (partial,) = tmp_path.glob(".run.ckpt.*.tmp")  # the killed save's own temporary file (unique name)
    assert partial.is_file() and run.is_file()
    assert read_checkpoint(run)["train_state"]["step"] == 4  # the last complete save survived the kill

    assert train(scenario, config, run, "--resume") == 0
    assert not partial.exists()
    ours_payload, theirs_payload = read_checkpoint(run), read_checkpoint(tmp_path / "reference.ckpt")
    assert ours_payload["train_state"]["step"] == theirs_payload["train_state"]["step"] == 8  # the trainer's count
    ours, theirs = ours_payload["state"], theirs_payload["state"]
    assert ours["stages"].keys() == theirs["stages"].keys()
    for name, weight in theirs["stages"].items():
        assert torch.equal(ours["stages"][name], weight), name
