"""Options and helpers shared by the CLI commands."""

from __future__ import annotations

import json
import math
import os
import random
import time
from enum import StrEnum
from pathlib import Path

import numpy as np
import torch
import typer

from rflscm.errors import ConfigError


class Device(StrEnum):
    """``--device`` choices."""

    auto = "auto"
    cpu = "cpu"
    cuda = "cuda"


class Interrupted(BaseException):
    """SIGINT or SIGTERM arrived (raised by the handler :func:`rflscm.cli.main` installs).  A command that knows
    what it saved re-raises it with ``saved`` (one clause: what is on disk, how to resume); ``main`` prints one
    line and exits 128 + the signal number.  A ``BaseException`` so that no ``except Exception`` swallows it."""

    def __init__(self, signum: int, saved: str | None = None) -> None:
        super().__init__(signum, saved)
        self.signum, self.saved = int(signum), saved


ForceOption = typer.Option(
    False, "--force", help="Replace output files that exist already (never an input of the command)."
)
DeviceOption = typer.Option(Device.auto, "--device", help="Compute device: auto (CUDA if present), cpu or cuda.")
SeedOption = typer.Option(0, "--seed", help="Random seed (integer; runs are repeatable for a given seed).")
THREADS_ENV = "RFLSCM_THREADS"
ThreadsOption = typer.Option(
    None,
    "--threads",
    metavar="N",
    show_default=False,
    help=f"CPU threads torch uses inside one operation (count; default: ${THREADS_ENV} if set, else torch's own "
    "default). On a busy machine 1 can be many times faster than more.",
)


def output_file(path: Path, option: str) -> Path:
    """Check an output file option before any work is done: a folder or an unwritable place is a
    :class:`ConfigError` (not a traceback after minutes of training).  Creates the parent folder."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{option} {path}: is a folder; give a file name (e.g. {path / 'out'}…).")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise ConfigError(f"{option} {path}: cannot create its folder ({reason}).") from None
    if not os.access(path.parent, os.W_OK):
        raise ConfigError(f"{option} {path}: its folder is not writable.")
    return path


def output_folder(path: Path, option: str) -> Path:
    """Like :func:`output_file` for an option naming a folder (created if needed)."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise ConfigError(f"{option} {path}: is a file; give a folder.")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        reason = exc.strerror or type(exc).__name__
        raise ConfigError(f"{option} {path}: cannot create the folder ({reason}).") from None
    return path


def check_numbers(**values: tuple[float | int | None, float, float]) -> None:
    """One validator for numeric options, called at the top of a command body: each ``name=(value, low, high)``
    must be finite and within ``[low, high]`` (None: not given).  The name is the option (``seed`` →
    ``--seed``).  Raises :class:`ConfigError` naming the option, the value and the range."""
    for name, (value, low, high) in values.items():
        if value is None:
            continue
        option = "--" + name.replace("_", "-")
        try:
            number = float(value)
        except (TypeError, ValueError, OverflowError):
            raise ConfigError(f"{option} must be a number (got {value!r}).") from None
        if not math.isfinite(number):
            raise ConfigError(f"{option} must be a finite number (got {value}).")
        if not low <= number <= high:
            raise ConfigError(f"{option} must be between {_shown(low)} and {_shown(high)} (got {_shown(value)}).")


def _shown(value: float) -> str:
    return str(value) if isinstance(value, int) else f"{value:g}"


SEED_MAX = 2**63 - 1
"""The largest ``--seed`` (torch's generator takes a 64-bit integer)."""


def refuse_inputs_inside(out: Path, inputs: list[Path | None], option: str = "--out") -> None:
    """A folder a command replaces (``--force``) must not hold one of its inputs."""
    root = os.path.realpath(out).rstrip(os.sep) + os.sep
    for source in inputs:
        if source is not None and os.path.realpath(source).startswith(root):
            raise ConfigError(
                f"{option} {out}: holds an input of this command ({source}); replacing the folder would destroy "
                f"that input — choose another {option}."
            )


def json_text(value: object) -> str:
    """JSON with every NaN or ±inf written as ``null`` (``json.dumps`` would write ``NaN``, which is not JSON)."""

    def clean(v: object) -> object:
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v

    return json.dumps(clean(value), indent=2, allow_nan=False)


def resolve_device(name: str | Device) -> torch.device:
    """``auto`` → CUDA when available, else CPU; ``cuda`` without a GPU is a clear error."""
    name = str(getattr(name, "value", name)).lower()
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
    """Seed Python, numpy and torch; a seed outside 0 … 2^63 − 1 is a :class:`ConfigError`."""
    check_numbers(seed=(seed, 0, SEED_MAX))
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


_COMMAND_START: list[float] = []


def mark_command_start(at: float | None = None) -> None:
    """Remember ``at`` (a ``time.perf_counter()`` reading; default now) as the start of the command being run
    (:func:`command_start`); the entry point calls it first."""
    _COMMAND_START[:] = [time.perf_counter() if at is None else at]


def command_start() -> float:
    """``time.perf_counter()`` at the start of the running command (now, when it was not marked): a ``--minutes``
    budget counts from there, so that the libraries' import and the scenario's loading are inside it."""
    return _COMMAND_START[0] if _COMMAND_START else time.perf_counter()


def budget_seconds(minutes: float | None, option: str = "--minutes") -> float | None:
    """The training time budget [s] of ``--minutes`` (None: none); a value that is not a positive finite number
    of minutes is a :class:`ConfigError`."""
    if minutes is None:
        return None
    if not (math.isfinite(minutes) and minutes > 0):
        raise ConfigError(f"{option} must be a positive number of minutes of training (got {minutes:g}).")
    return 60.0 * minutes


def budget_summary(summary: dict[str, float]) -> str | None:
    """One line on a time-budget training run (None for a run without a budget): the training, the pass after it
    (how many training pairs got their own corrections) and the whole fit against the budget."""
    budget = summary.get("budget_s")
    if budget is None:
        return None
    stopped = "the budget stopped it" if summary.get("stopped_by_budget") else "it stopped before the budget"
    line = (
        f"trained {summary['steps']:.0f} steps ({summary['passes']:.1f} passes) in {summary['train_time_s']:.1f} s "
        f"of a {budget / 60:g}-minute budget; {stopped}"
    )
    if "finish_s" in summary:
        line += f"; the pass after training took {summary['finish_s']:.1f} s"
        pairs, corrected = summary.get("training_pairs"), summary.get("corrected_pairs")
        if pairs is not None and corrected is not None:
            line += f" and corrected {corrected:.0f} of {pairs:.0f} training pairs"
            wnomp = summary.get("wnomp_pairs") or 0.0
            borrowed = summary.get("borrowed_pairs") or 0.0
            level_only = max((summary.get("rendered_pairs") or 0.0) - corrected, 0.0)
            by_budget = " (rendering them all did not fit the budget)" if summary.get("budget_choice") else ""
            if corrected < pairs and wnomp:
                line += (
                    f" ({wnomp:.0f} others get WNOMP's APS of their own reports, which predicted held-aside reports "
                    f"better{by_budget}: give more `--minutes` to correct them all)"
                )
            elif corrected < pairs and borrowed:
                line += (
                    f" ({borrowed:.0f} others borrow the APS of the nearest rendered grid of their cell with their own "
                    f"anchor, which predicted held-aside reports better{by_budget}: give more `--minutes` to correct them "
                    "all)"
                )
            elif corrected < pairs and level_only:
                line += (
                    f" ({level_only:.0f} others were rendered with the level correction only: give more `--minutes` "
                    "to correct them all)"
                )
            elif corrected < pairs:
                line += " (the others keep the level correction: give more `--minutes` to correct them all)"
    if "total_s" in summary:
        line += f"; {summary['total_s']:.1f} s in all"
    return line


def budget_note(summary: dict[str, float]) -> str | None:
    """A warning when a training run showed the model each training pair fewer than ``FEW_PASSES`` times."""
    passes = summary.get("passes")
    if passes is None or passes >= FEW_PASSES:
        return None
    more = (
        "more time (`--minutes`)"
        if "budget_s" in summary
        else "more steps (`train.steps` in a YAML config, `--config FILE.yaml`)"
    )
    return (
        f"[yellow]note:[/yellow] the run showed the model each training pair only {passes:.2g} times on average; "
        f"expect it to underfit. Give it {more} or train `--config full` on a GPU."
    )
