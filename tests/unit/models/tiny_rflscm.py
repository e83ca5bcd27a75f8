"""A tiny RF-LSCM configuration shared by the model tests (a few seconds of training on a tiny scenario)."""

from __future__ import annotations

from collections.abc import Callable


class Interrupt(Exception):
    """Raised by :func:`stop_at`'s callback: a training run killed part-way."""


def stop_at(step: int) -> Callable[[dict], None]:
    """A training callback that raises :class:`Interrupt` once ``step`` steps are done."""

    def callback(metrics: dict) -> None:
        if metrics["step"] == step:
            raise Interrupt

    return callback


def tiny_config(**sections: dict) -> dict:
    """The tiny config with each ``section`` (``train={"steps": 4}``, …) merged over its defaults."""
    cfg = {
        "prior": {"enabled": False},
        "field": {"voxel_m": 20.0, "delta_rank": 2, "feature_rank": 2, "feature_dim": 4},
        "decoder": {"hidden": 16},
        "render": {"step_m": 8.0},
        "hitam": {"top_k": 3, "warmup_steps": 4, "ramp_steps": 2},
        "train": {
            "steps": 8,
            "batch_pairs": 4,
            "pairs_per_cell": 2,
            "val_pairs": 2,
            "val_every": 4,
            "checkpoint_every": 4,
        },
    }
    for name, values in sections.items():
        cfg[name] = {**cfg.get(name, {}), **values}
    return cfg
