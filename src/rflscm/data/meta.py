"""``scenario.yaml``: the typed, strict-key description of a scenario folder.

Example::

    name: munich-default
    description: free text (optional)
    origin: null                  # or {lat: 48.14, lon: 11.57, height_m: 0}
    rsrp_threshold_dbm: -120.0
    reporting: {csi: {rule: top_n, top_n: 4, serving_only: true}}  # optional, see rflscm.data.reporting
    frequencies_hz: [2.1e9, 3.5e9]
    codebooks: {ssb8: {type: ssb}, csi32: {type: dft}}
    rounds: {1: {cells: cells_round1.csv}, 2: {cells: cells_round2.csv}}
    grids: grids.parquet
    measurements: measurements.parquet
    point_cloud: point_cloud.ply  # optional
    truth: truth                  # optional folder written by the simulator
    simulation: {}                # optional provenance, kept as is

File names are relative to the scenario folder.  PyYAML reads ``2.1e9``
(no sign after ``e``) as text; numbers written that way are accepted.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from rflscm.antenna import Codebook, codebook_from_dict
from rflscm.config import from_dict, to_dict
from rflscm.data.columns import fmt_list, fmt_number
from rflscm.data.geo import Origin
from rflscm.data.reporting import ReportingRule, reporting_from_dict
from rflscm.data.terrain import Terrain, load_terrain
from rflscm.errors import ConfigError

RSRP_MIN_DBM = -156.0
"""Lowest reportable RSRP [dBm] (TS 38.133 RSRP report mapping)."""
RSRP_MAX_DBM = -31.0
"""Highest reportable RSRP [dBm] (TS 38.133 RSRP report mapping)."""
MAX_FREQUENCY_HZ = 3e11
"""Highest carrier accepted [Hz] (300 GHz: beyond any 5G/6G band; a larger value is a unit mistake)."""
MAX_ROUND = 2**31 - 1
"""Largest round number (it must fit the measurements table's integer column)."""


@dataclass(frozen=True)
class ScenarioMeta:
    """The contents of ``scenario.yaml`` (file names relative to the scenario folder)."""

    name: str
    frequencies_hz: tuple[float, ...]
    """Carriers present [Hz]; every cell's ``freq_hz`` is one of them."""
    codebooks: dict[str, Codebook]
    """Named beam codebooks referenced by the cells tables' ``ssb_codebook`` / ``csi_codebook``."""
    rounds: dict[int, str]
    """Measurement round → cells table file; round 1 is required."""
    grids: str
    measurements: str | None = None
    """Measurements table; ``None`` for a scenario without measurements (e.g. a what-if configuration)."""
    description: str = ""
    origin: Origin | None = None
    """Geodetic origin of the ENU frame; needed when tables give lat/lon/height_m."""
    rsrp_threshold_dbm: float = -120.0
    """Reporting threshold r_th [dBm]: beams below it are missing (NaN)."""
    point_cloud: str | None = None
    truth: str | None = None
    reporting: dict[str, ReportingRule] = field(default_factory=dict)
    """Reporting rule per beam type (:mod:`rflscm.data.reporting`); absent = ``rsrp_threshold_dbm`` for both."""
    simulation: dict[str, Any] = field(default_factory=dict)
    """Free-form provenance written by the simulator, kept as is."""
    terrain: str | None = None
    """DEM GeoTIFF or XYZ table (:mod:`rflscm.data.terrain`); with it ``height_m`` is above ground."""

    @property
    def ground(self) -> Terrain | None:
        """The loaded terrain (``None`` without ``terrain:`` or when read without a scenario folder)."""
        terrain: Terrain | None = getattr(self, "_terrain", None)
        return terrain

    def to_dict(self) -> dict[str, Any]:
        """Plain (YAML-safe) mapping in the order of the example above."""
        return {
            "name": self.name,
            "description": self.description,
            "origin": None if self.origin is None else to_dict(self.origin),
            "rsrp_threshold_dbm": self.rsrp_threshold_dbm,
            **({"reporting": {k: r.to_dict() for k, r in self.reporting.items()}} if self.reporting else {}),
            "frequencies_hz": list(self.frequencies_hz),
            "codebooks": {name: to_dict(cb) for name, cb in self.codebooks.items()},
            "rounds": {r: {"cells": f} for r, f in sorted(self.rounds.items())},
            "grids": self.grids,
            "measurements": self.measurements,
            "point_cloud": self.point_cloud,
            "truth": self.truth,
            **({"terrain": self.terrain} if self.terrain else {}),
            "simulation": self.simulation,
        }

    def content(self) -> dict[str, Any]:
        """What the scenario *says*, without file names (for equality across formats)."""
        d = self.to_dict()
        for key in ("rounds", "grids", "measurements", "point_cloud", "truth"):
            d.pop(key)
        d.pop("terrain", None)
        return d


_REQUIRED = ("name", "frequencies_hz", "codebooks", "rounds", "grids")


def meta_from_dict(data: dict[str, Any], where: str = "scenario.yaml", root: Path | None = None) -> ScenarioMeta:
    """Validate and build :class:`ScenarioMeta` from the YAML mapping; errors name ``where`` and the key.

    ``root`` (the scenario folder) loads file codebooks (``type: weights`` / ``pattern``) at once.
    """
    valid = [f.name for f in dataclasses.fields(ScenarioMeta)]
    unknown = sorted(str(k) for k in set(data) - set(valid))
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(repr(k) for k in unknown)}; valid keys: {', '.join(valid)}."
        )
    missing = [k for k in _REQUIRED if data.get(k) in (None, "", [], {})]
    if missing:
        raise ConfigError(f"{where}: missing key(s) {', '.join(missing)}; required: {', '.join(_REQUIRED)}.")
    try:
        meta = ScenarioMeta(
            name=_text(data["name"], "name"),
            description=_text(data.get("description") or "", "description"),
            origin=None if data.get("origin") is None else from_dict(Origin, data["origin"], prefix="origin"),
            rsrp_threshold_dbm=_threshold(data.get("rsrp_threshold_dbm", -120.0)),
            frequencies_hz=_frequencies(data["frequencies_hz"]),
            codebooks=_codebooks(data["codebooks"], root),
            rounds=_rounds(data["rounds"]),
            grids=_text(data["grids"], "grids"),
            measurements=_optional_text(data.get("measurements"), "measurements"),
            point_cloud=_optional_text(data.get("point_cloud"), "point_cloud"),
            truth=_optional_text(data.get("truth"), "truth"),
            simulation=_simulation(data.get("simulation")),
            terrain=_optional_text(data.get("terrain"), "terrain"),
            reporting=reporting_from_dict(data.get("reporting")),
        )
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None
    if root is not None and meta.terrain is not None:
        object.__setattr__(meta, "_terrain", load_terrain(root, meta.terrain, meta.origin))
    return meta


def _number(value: object, key: str) -> float:
    if isinstance(value, str):
        try:
            return float(value.strip())
        except ValueError:
            pass
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ConfigError(f"`{key}` must be a number (got {value!r}).")
    return float(value)


def _text(value: object, key: str) -> str:
    if not isinstance(value, str):
        raise ConfigError(f"`{key}` must be text (got {value!r}).")
    return value


def _optional_text(value: object, key: str) -> str | None:
    return None if value in (None, "") else _text(value, key)


def _threshold(value: object) -> float:
    th = _number(value, "rsrp_threshold_dbm")
    if not RSRP_MIN_DBM <= th <= RSRP_MAX_DBM:
        raise ConfigError(
            f"`rsrp_threshold_dbm` = {th!r} is outside the reportable range −156…−31 dBm; "
            "give the reporting threshold in dBm (e.g. -120)."
        )
    return th


def frequency_unit_hint(freq: float) -> str | None:
    """A hint when a carrier given in Hz looks like GHz, MHz or kHz (``None`` when it looks like Hz)."""
    for limit, scale, unit in ((1e3, 1e9, "GHz"), (1e6, 1e6, "MHz"), (1e8, 1e3, "kHz")):
        if 0 < freq < limit:
            return f"looks like {unit}; did you mean {fmt_number(freq * scale)} Hz?"
    return None


def _frequencies(value: object) -> tuple[float, ...]:
    items = value if isinstance(value, (list, tuple)) else [value]
    out = []
    for i, item in enumerate(items):
        freq = _number(item, f"frequencies_hz[{i}]")
        hint = frequency_unit_hint(freq)
        if not 0 < freq <= MAX_FREQUENCY_HZ or hint:
            allowed = f"must be a carrier in Hz, 0 < f ≤ {MAX_FREQUENCY_HZ:.0e} Hz."
            raise ConfigError(f"`frequencies_hz[{i}]` = {item!r} {hint or allowed}")
        out.append(freq)
    if len(set(out)) != len(out):
        raise ConfigError(f"`frequencies_hz` lists a carrier twice ({fmt_list(fmt_number(f) for f in out)}).")
    return tuple(out)


def _codebooks(value: object, root: Path | None = None) -> dict[str, Codebook]:
    if not isinstance(value, dict):
        raise ConfigError(f"`codebooks` must map names to codebooks, e.g. {{ssb8: {{type: ssb}}}} (got {value!r}).")
    books = {}
    for name, spec in value.items():
        key = str(name)
        books[key] = codebook_from_dict(spec, where=f"codebooks.{key}", root=root)
    return books


def _rounds(value: object) -> dict[int, str]:
    if not isinstance(value, dict):
        raise ConfigError("`rounds` must map round numbers to {cells: FILE}, e.g. {1: {cells: cells.csv}}.")
    rounds: dict[int, str] = {}
    for key, spec in value.items():
        if isinstance(key, bool) or not isinstance(key, int) or not 1 <= key <= MAX_ROUND:
            raise ConfigError(f"`rounds` keys must be round numbers 1, 2, … up to {MAX_ROUND} (got {key!r}).")
        if isinstance(spec, str):
            spec = {"cells": spec}
        if not isinstance(spec, dict) or set(spec) != {"cells"}:
            raise ConfigError(f"`rounds.{key}` must be {{cells: FILE}} (got {spec!r}); valid keys: cells.")
        rounds[key] = _text(spec["cells"], f"rounds.{key}.cells")
    if 1 not in rounds:
        raise ConfigError(
            f"`rounds` must define round 1 (the configuration models are fitted on); got {sorted(rounds)}."
        )
    return dict(sorted(rounds.items()))


def _simulation(value: object) -> dict[str, Any]:
    if value is None:
        return {}
    if not isinstance(value, dict):
        raise ConfigError(f"`simulation` must be a mapping (got {value!r}).")
    return dict(value)
