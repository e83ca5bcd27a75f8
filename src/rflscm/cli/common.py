"""Options and helpers shared by the CLI commands."""

from __future__ import annotations

import random

import numpy as np
import torch
import typer

from rflscm.errors import ConfigError

DeviceOption = typer.Option("auto", "--device", help="Compute device: auto (CUDA if present), cpu or cuda.")
SeedOption = typer.Option(0, "--seed", help="Random seed (runs are repeatable for a given seed).")


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
