"""``--preset``, ``--config FILE.yaml`` and ``--set SECTION.KEY=VALUE``: a model config a user can write.

The chosen preset (``quick`` or ``full``) is the base; a YAML file given to ``--config`` holds only the keys
that differ from it; each ``--set`` changes one key on top of both.  ``--config quick`` / ``--config full``
still name a preset.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import typer

from rflscm.errors import ConfigError

PRESET_NAMES = ("quick", "full")
PresetOption = typer.Option(
    None, "--preset", help="Preset the --config YAML and --set start from: quick or full (default: quick)."
)
SetOption = typer.Option(
    [],
    "--set",
    metavar="SECTION.KEY=VALUE",
    help="Change one model setting (repeatable), e.g. --set train.steps=500 --set prior.enabled=false.",
)


def model_config(
    model: str, config: str, preset: str | None, sets: list[str], under: dict[str, Any] | None = None
) -> str | dict[str, Any]:
    """What to hand ``MODEL_REGISTRY[model].build``: the preset name when nothing overrides it, else the merged
    mapping (preset ← ``under`` ← YAML ← ``--set``), already checked against the model's config class.  ``under``:
    settings a command chooses itself (the demo's WNOMP settings for RF-LSCM's fallback), which the user's YAML and
    ``--set`` still override."""
    from rflscm.config import apply_sets, from_dict, load_yaml, merge_config, to_dict
    from rflscm.geometry import AngleGrid
    from rflscm.models import MODEL_REGISTRY

    if preset is not None and preset not in PRESET_NAMES:
        raise ConfigError(f"--preset {preset!r} is not a preset; choose one of: {', '.join(PRESET_NAMES)}.")
    is_file = config not in PRESET_NAMES
    if is_file and preset is None:
        preset = "quick"
    if not is_file:
        if preset is not None and preset != config:
            raise ConfigError(f"--config {config} and --preset {preset} name two presets; give one.")
        preset = config
    if not is_file and not sets and not under:
        return config
    base = MODEL_REGISTRY[model].build(preset, AngleGrid(), "cpu").config  # type: ignore[attr-defined]  # all have one
    cls = type(base)
    data = merge_config(to_dict(base), under or {})
    if is_file:
        path = Path(config)
        if path.suffix.lower() not in (".yaml", ".yml") and not path.is_file():
            raise ConfigError(f"--config {config!r}: give a preset ({', '.join(PRESET_NAMES)}) or a YAML file.")
        user = load_yaml(path)
        if user.get("name") == model and "name" not in data:
            user.pop("name")
        merged = merge_config(data, user)
        try:
            from_dict(cls, merged)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
        data = merged
    data = apply_sets(cls, data, sets)
    from_dict(cls, data)  # cross-field checks of the config's own __post_init__, before any work
    return data
