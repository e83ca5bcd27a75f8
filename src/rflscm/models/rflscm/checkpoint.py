"""RF-LSCM's checkpoint state: save, load and the resume checks, and the one compatibility policy.

**Policy (0.x):** a checkpoint's model state carries ``STATE_VERSION``.  A checkpoint of another version (the
layouts before issue 24: per-option migrations of removed knobs, renamed weights) is refused in one line that
says to retrain; nothing is migrated.  Removed options in a user's YAML still get their own one-line message
from the config sections' ``REMOVED`` tables (:func:`rflscm.config.from_dict`).
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from rflscm.config import from_dict, to_dict
from rflscm.errors import CheckpointError, ConfigError
from rflscm.fields import TensorVM
from rflscm.geometry import AngleGrid
from rflscm.models.rflscm.corrections import PairCorrections
from rflscm.models.rflscm.scene import (
    SceneInfo,
    prior_from_state,
    prior_state,
    surfaces_from_state,
    surfaces_state,
)

if TYPE_CHECKING:
    from rflscm.models.rflscm.config import RFLSCMConfig
    from rflscm.models.rflscm.model import RFLSCM

STATE_VERSION = 2
"""Version of the model state below; bump it when its layout changes (older checkpoints are then refused)."""


def model_state(model: RFLSCM) -> dict[str, Any]:
    """The model's checkpoint state: config, scene, prior, surfaces, stage weights, schedule position and the pair
    corrections (tensors and plain values only; the trainer saves its own state beside it)."""
    return {
        "version": STATE_VERSION,
        "config": to_dict(model.config),
        "angle_grid": model.angle_grid.to_dict(),
        "scene": model.scene.to_dict() if model.scene is not None else None,
        "prior": prior_state(model.prior),
        "surfaces": surfaces_state(model.surfaces),
        "stages": {k: v.detach().cpu().clone() for k, v in model.stages.state_dict().items()},
        "position": model.position,
        "corrections": model.corrections.to_state(),
    }


def check_version(state: dict[str, Any]) -> None:
    """Refuse a state of another layout in one line (the 0.x policy above)."""
    version = state.get("version") if isinstance(state, dict) else None
    if version != STATE_VERSION:
        raise CheckpointError(
            f"the checkpoint was written by another version of rflscm (model state {version or 1}, this version "
            f"reads {STATE_VERSION}); retrain it with this version."
        )


def restore(cls: type[RFLSCM], state: dict[str, Any], device: torch.device | str = "cpu") -> RFLSCM:
    """A fitted model from :func:`model_state`'s ``state``."""
    check_version(state)
    try:
        config: RFLSCMConfig = from_dict(cls.config_class, state["config"])
    except ConfigError as exc:
        raise CheckpointError(f"the checkpoint's config does not fit this version ({exc}); retrain it.") from None
    model = cls(config, AngleGrid.from_dict(state["angle_grid"]), device)
    if state["scene"] is None:
        raise CheckpointError("this checkpoint holds an unfitted model.")
    model.scene = SceneInfo.from_dict(state["scene"])
    prior = prior_from_state(state["prior"])
    model.prior = prior.to(model.device) if prior is not None else None
    surfaces = surfaces_from_state(state.get("surfaces"))
    model.surfaces = surfaces.to(model.device) if surfaces is not None else None
    model._build_stages(model.scene.frame)
    load_stage_weights(model, state["stages"])
    model.position = float(state["position"])
    model.corrections = PairCorrections.from_state(state.get("corrections"), model.angle_grid.num_bins, model.device)
    return model


def load_stage_weights(model: RFLSCM, weights: dict[str, torch.Tensor]) -> None:
    """Load stage ``weights`` into ``model`` (upsampling its VM tensors to the saved resolution first)."""
    for name, module in model.stages.named_modules():
        if isinstance(module, TensorVM):
            nx, ny, nz = (int(weights[f"{name}.lines.{a}"].shape[2]) for a in range(3))
            res = (nx, ny, nz)
            if res != module.resolution:
                module.upsample(res)
    try:
        model.stages.load_state_dict(weights)
    except (RuntimeError, KeyError) as exc:
        first = str(exc).strip().splitlines()[-1].strip()
        raise CheckpointError(
            f"the checkpoint's weights do not fit this version of {model.name!r} ({first}); retrain it with this version."
        ) from None
    model.stages.to(model.device)


def check_resume(model: RFLSCM, payload: dict[str, Any], path: str | Path) -> dict[str, Any]:
    """The model state of checkpoint ``payload`` (of ``path``) if ``model`` may resume from it: the same model,
    scenario, state version and config; else a one-line :class:`CheckpointError` saying what differs."""
    state = payload["state"]
    if payload["model"] != model.name:
        raise CheckpointError(
            f"{path}: cannot resume: it holds a {payload['model']!r} model, not {model.name!r}; train {model.name} "
            "into another file, or without --resume to overwrite it."
        )
    if payload["fingerprint"] != model.fingerprint:
        raise CheckpointError(f"{path}: cannot resume: it was trained on another scenario (or other data).")
    try:
        check_version(state)
    except CheckpointError as exc:
        raise CheckpointError(f"{path}: cannot resume: {exc}") from None
    theirs, ours = state["config"], to_dict(model.config)
    # an option added since the checkpoint was written reads as its default, the behaviour it was trained with (a
    # removed or invalid option is reported below as a change)
    with contextlib.suppress(ConfigError):
        theirs = to_dict(from_dict(type(model.config), theirs))
    steps_now, steps_then = ours["train"]["steps"], dict(theirs.get("train") or {}).get("steps")
    if steps_now != steps_then:
        raise CheckpointError(
            f"{path}: cannot resume: it was trained towards `train.steps` = {steps_then}, this run asks for "
            f"{steps_now}; the learning-rate schedule (lr_decay ** (step / steps)) depends on it. Resume with "
            f"`train.steps: {steps_then}`, or train afresh without --resume."
        )
    if ours != theirs:
        keys = changed_keys(ours, theirs)
        raise CheckpointError(
            f"{path}: cannot resume: the checkpoint was trained with another config (changed: "
            f"{', '.join(keys[:5]) or 'layout'}); resume with its config or train afresh without --resume."
        )
    return state


def changed_keys(a: object, b: object, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two nested config dicts (lists and tuples alike)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out: list[str] = []
        for key in sorted(set(a) | set(b), key=str):
            out += changed_keys(a.get(key), b.get(key), f"{prefix}.{key}" if prefix else str(key))
        return out
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return [] if list(a) == list(b) else [prefix]
    return [] if a == b else [prefix]
