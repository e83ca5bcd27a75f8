"""Options and helpers shared by the CLI commands."""

from __future__ import annotations

import os
import random

import numpy as np
import torch
import typer

from rflscm.errors import ConfigError

DeviceOption = typer.Option("auto", "--device", help="Compute device: auto (CUDA if present), cpu or cuda.")
SeedOption = typer.Option(0, "--seed", help="Random seed (runs are repeatable for a given seed).")
THREADS_ENV = "RFLSCM_THREADS"
ThreadsOption = typer.Option(
    None, "--threads", metavar="N", show_default=False,
    help=f"CPU threads torch uses inside one operation (default: ${THREADS_ENV} if set, else torch's own "
    "default). On a busy machine 1 can be many times faster than more.",
)  # fmt: skip


def resolve_device(name: str) -> torch.device:
    """``auto`` → CUDA when available, else CPU; ``cuda`` without a GPU is a clear error."""
    name = name.lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ConfigError("--device cuda was asked for but no CUDA GPU is available; use --device cpu or auto.")
        return torch.device(name)
    if name == "cpu":
        return torch.device("cpu")
    raise ConfigError(f"--device must be auto, cpu or cuda (got {name!r}).")


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)
    torch.manual_seed(seed)


def set_threads(threads: int | None) -> int | None:
    """``torch.set_num_threads`` from ``--threads`` or, without it, from ``$RFLSCM_THREADS``; with neither,
    torch keeps its default.  Returns the number set (None: left alone); a number below 1 or a value that
    is not a whole number is a :class:`ConfigError`."""
    source = "--threads"
    if threads is None:
        raw = os.environ.get(THREADS_ENV, "").strip()
        if not raw:
            return None
        source = f"the environment variable {THREADS_ENV}"
        try:
            threads = int(raw)
        except ValueError:
            raise ConfigError(f"{source} must be a whole number of threads, at least 1 (got {raw!r}).") from None
    if threads < 1:
        raise ConfigError(f"{source} must be at least 1 CPU thread (got {threads}).")
    torch.set_num_threads(threads)
    return threads


FEW_PASSES = 4.0
"""Below this many passes over the training pairs a radiance-field model is far from trained (BENCHMARKS.md)."""


def budget_note(summary: dict[str, float]) -> str | None:
    """A warning when a training run showed the model each training pair fewer than ``FEW_PASSES`` times."""
    passes = summary.get("passes")
    if passes is None or passes >= FEW_PASSES:
        return None
    return (
        f"[yellow]note:[/yellow] the run showed the model each training pair only {passes:.2g} times on average; "
        f"expect it to underfit. Give it more steps (`train.steps` in a YAML config, `--config FILE.yaml`) or "
        f"train `--config full` on a GPU."
    )
