"""Ground truth by ray tracing (SPEC §6): scene backends → paths → true APS and RSRP → scenarios.

* :mod:`rflscm.sim.backend` — the :class:`SceneBackend` protocol and the path-table schema;
* :mod:`rflscm.sim.procedural` — :class:`ProceduralCity`, a fast box city with no dependency;
* :mod:`rflscm.sim.sionna_rt` — Sionna RT's city scenes (the ``rt`` extra);
* :mod:`rflscm.sim.paths` — paths → true APS (binned) and true RSRP for any antenna;
* :mod:`rflscm.sim.noise` — measurement noise, quantisation, reporting threshold;
* :mod:`rflscm.sim.builder` — :func:`build_scenario` with :class:`SimulationConfig`;
* :mod:`rflscm.sim.truth` — ``truth/`` files and :func:`load_true_aps` (the oracle that answers with
  them is an evaluation device: :mod:`rflscm.eval.oracle`).
"""

from __future__ import annotations

import inspect
from importlib import resources
from pathlib import Path
from typing import Any

from rflscm.errors import ConfigError
from rflscm.sim.backend import PATH_COLUMNS, SceneBackend, empty_path_table
from rflscm.sim.builder import CODEBOOKS, SimulationConfig, build_scenario
from rflscm.sim.noise import MeasurementModel, measure
from rflscm.sim.procedural import MATERIALS, PROCEDURAL_SCENES, ProceduralCity
from rflscm.sim.truth import TrueAPS, load_true_aps

BACKENDS = ("procedural", "sionna")
"""Names accepted by :func:`make_backend` (``rflscm simulate --backend``)."""


def make_backend(
    name: str, scene: str | None = None, seed: int = 0, device: str = "cpu", options: dict[str, Any] | None = None
) -> SceneBackend:
    """A scene backend by name.

    Args:
        name: ``procedural`` or ``sionna``.
        scene: a :data:`PROCEDURAL_SCENES` preset (default ``city``) or a Sionna scene
            (default ``munich``; see :func:`rflscm.sim.sionna_rt.available_scenes`).
        seed: layout seed of the procedural city (Sionna scenes are fixed).
        device: ``cpu``, ``cuda`` or ``auto`` for Sionna; the procedural backend runs on the CPU.
        options: extra keyword arguments of the backend's constructor.
    """
    options = dict(options or {})
    if name == "procedural":
        _check_options(ProceduralCity, options, name, reserved=("seed",))
        return ProceduralCity.from_scene(scene or "city", seed=seed, **options)
    if name == "sionna":
        from rflscm.sim.sionna_rt import SionnaSceneBackend

        _check_options(SionnaSceneBackend, options, name, reserved=("scene", "device"))
        return SionnaSceneBackend(scene or "munich", device=device, **options)
    raise ConfigError(f"unknown backend {name!r}; valid: {', '.join(BACKENDS)}.")


def _check_options(cls: type, options: dict[str, Any], name: str, reserved: tuple[str, ...]) -> None:
    """Unknown ``backend_options`` keys (or ones set elsewhere) are a :class:`ConfigError` listing the valid ones."""
    valid = [p for p in inspect.signature(cls).parameters if p not in reserved]
    unknown = sorted(set(options) - set(valid))
    if unknown:
        raise ConfigError(
            f"`backend_options` for the {name} backend: unknown key(s) {', '.join(map(repr, unknown))}; "
            f"valid keys: {', '.join(valid)}."
        )


def default_scenario_path() -> Path:
    """Folder of the scenario that ships with the package (made by ``scripts/make_default_scenario.sh``)."""
    return Path(str(resources.files("rflscm") / "assets" / "scenarios" / "default"))


__all__ = [
    "BACKENDS",
    "CODEBOOKS",
    "MATERIALS",
    "PATH_COLUMNS",
    "PROCEDURAL_SCENES",
    "MeasurementModel",
    "ProceduralCity",
    "SceneBackend",
    "SimulationConfig",
    "TrueAPS",
    "build_scenario",
    "default_scenario_path",
    "empty_path_table",
    "load_true_aps",
    "make_backend",
    "measure",
]
