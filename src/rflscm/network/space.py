"""The search space of ``rflscm optimize``: per-cell options for tilts, azimuth and SSB codebook.

A spec comes from a YAML file and/or CLI flags, with a planner's defaults::

    defaults:
      mech_tilt_deg: {min: 0, max: 15, step: 1}        # absolute mechanical down-tilt [deg]
      elec_tilt_deg: {min: 0, max: 15, step: 1}        # absolute electrical down-tilt [deg]
      azimuth_offset_deg: {min: -30, max: 30, step: 5} # around the current azimuth [deg]
      ssb_codebooks: all                               # or a list of scenario.yaml `ssb` codebooks
    cells:                                             # per-cell overrides of `defaults`
      201: {mech_tilt_deg: {min: 2, max: 8, step: 1}}
    frozen: [101, 102]                                 # cells that must not change
    max_changed_cells: 8                               # default 8; null = no limit
    max_step:                                          # largest change per cell in one recommendation
      mech_tilt_deg: 4                                 #   (defaults: :data:`DEFAULT_MAX_STEP`)
      elec_tilt_deg: 4
      total_tilt_deg: 4                                # |Δ mechanical + Δ electrical|
      azimuth_deg: 10

The current value of every variable is always an option, so "leave the cell alone" is in the
space.  Options are indices into per-cell value lists (:class:`CellOptions`).  Ranges beyond
:data:`PHYSICAL_LIMITS` are refused.  Cells that share an antenna panel (the cells table's optional
``panel_id`` column; without it, cells of one site with the same azimuth) share their mechanical tilt
and azimuth: the search moves them together (docs/optimize.md).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from rflscm.errors import ConfigError

VARIABLES = ("ssb_codebook", "elec_tilt_deg", "mech_tilt_deg", "azimuth_deg")
"""The searched variables, in the order coordinate descent visits them."""
DEFAULT_RANGES = {
    "mech_tilt_deg": {"min": 0.0, "max": 15.0, "step": 1.0},
    "elec_tilt_deg": {"min": 0.0, "max": 15.0, "step": 1.0},
    "azimuth_offset_deg": {"min": -30.0, "max": 30.0, "step": 5.0},
}
PHYSICAL_LIMITS = {
    "mech_tilt_deg": (-10.0, 20.0),
    "elec_tilt_deg": (-5.0, 20.0),
    "azimuth_offset_deg": (-60.0, 60.0),
}
"""What an antenna installation allows [deg]: mechanical down-tilt brackets reach −10…20°, remote electrical
tilt −5…20°, and an azimuth offset beyond ±60° turns a sector of a three-sector site into its neighbour's."""
DEFAULT_MAX_STEP = {"mech_tilt_deg": 4.0, "elec_tilt_deg": 4.0, "total_tilt_deg": 4.0, "azimuth_deg": 10.0}
"""The largest change of one cell in one recommendation [deg] (a drive test checks each step)."""
DEFAULT_MAX_CHANGED = 8
"""Cells one recommendation may change by default."""
SHARED_VARIABLES = ("mech_tilt_deg", "azimuth_deg")
"""Variables that cells sharing an antenna panel share (electrical tilt and codebook stay per cell)."""
_RANGE_KEYS = tuple(DEFAULT_RANGES)
_TOP_KEYS = {"defaults", "cells", "frozen", "max_changed_cells", "max_step"}
_CELL_KEYS = {*_RANGE_KEYS, "ssb_codebooks"}


@dataclass(frozen=True)
class CellOptions:
    """The values one cell may take; ``current`` holds the index of its present configuration."""

    cell_id: int
    values: dict[str, tuple[Any, ...]]
    """Variable → allowed values (azimuths absolute, clockwise from north, 0…360)."""
    current: tuple[int, ...]
    """Index of the present value of each variable of :data:`VARIABLES`."""

    def sizes(self) -> tuple[int, ...]:
        return tuple(len(self.values[v]) for v in VARIABLES)

    def config(self, index: tuple[int, ...]) -> dict[str, Any]:
        """Values of a configuration given by one index per variable."""
        return {v: self.values[v][i] for v, i in zip(VARIABLES, index)}

    @property
    def frozen(self) -> bool:
        return all(n == 1 for n in self.sizes())


@dataclass(frozen=True)
class SearchSpace:
    cells: tuple[CellOptions, ...]
    max_changed_cells: int | None
    max_total_tilt_step: float | None = None
    """Largest |Δ mechanical + Δ electrical tilt| of one cell [deg] (None: no limit)."""
    panels: tuple[tuple[int, ...], ...] = ()
    """Positions of cells that share an antenna panel (groups of two or more)."""

    def free_cells(self) -> list[int]:
        """Positions (in :attr:`cells`) of the cells with more than one option."""
        return [i for i, c in enumerate(self.cells) if not c.frozen]

    def panel_of(self, pos: int) -> tuple[int, ...]:
        """Positions of the cells sharing ``pos``'s antenna panel (``(pos,)`` when it has its own)."""
        for group in self.panels:
            if pos in group:
                return group
        return (pos,)

    def tilt_ok(self, pos: int, index: tuple[int, ...]) -> bool:
        """Whether ``index`` keeps cell ``pos``'s total tilt change within :attr:`max_total_tilt_step`."""
        if self.max_total_tilt_step is None:
            return True
        opts = self.cells[pos]
        new, old = opts.config(index), opts.config(opts.current)
        delta = new["mech_tilt_deg"] - old["mech_tilt_deg"] + new["elec_tilt_deg"] - old["elec_tilt_deg"]
        return abs(delta) <= self.max_total_tilt_step + 1e-9

    def follow(
        self, pos: int, index: tuple[int, ...], other: int, other_index: tuple[int, ...]
    ) -> tuple[int, ...] | None:
        """``other``'s index with its shared variables moved by the change ``index`` makes to cell ``pos``
        (None when ``other`` has no such option)."""
        a, b = self.cells[pos], self.cells[other]
        out = list(other_index)
        for var in SHARED_VARIABLES:
            k = VARIABLES.index(var)
            delta = a.values[var][index[k]] - a.values[var][a.current[k]]
            target = b.values[var][b.current[k]] + delta
            if var == "azimuth_deg":
                target %= 360.0
            matches = [i for i, v in enumerate(b.values[var]) if abs(v - target) < 1e-6]
            if not matches:
                return None
            out[k] = matches[0]
        return tuple(out)

    def tie(self, config: list[tuple[int, ...]]) -> list[tuple[int, ...]]:
        """``config`` made feasible: a cell beyond the total-tilt step goes back to its present tilts, and the
        cells of a panel follow its first changed member (or all go back to their shared present values)."""
        config = [tuple(c) for c in config]
        for pos, opts in enumerate(self.cells):
            if not self.tilt_ok(pos, config[pos]):
                index = list(config[pos])
                for var in ("mech_tilt_deg", "elec_tilt_deg"):
                    k = VARIABLES.index(var)
                    index[k] = opts.current[k]
                config[pos] = tuple(index)
        for group in self.panels:
            lead = next(
                (
                    p
                    for p in group
                    if any(
                        config[p][VARIABLES.index(v)] != self.cells[p].current[VARIABLES.index(v)]
                        for v in SHARED_VARIABLES
                    )
                ),
                group[0],
            )
            for other in group:
                if other == lead:
                    continue
                moved = self.follow(lead, config[lead], other, config[other])
                if moved is None or not self.tilt_ok(other, moved):
                    for p in group:  # the panel stays where it is
                        index = list(config[p])
                        for var in SHARED_VARIABLES:
                            k = VARIABLES.index(var)
                            index[k] = self.cells[p].current[k]
                        config[p] = tuple(index)
                    break
                config[other] = moved
        return config

    def size_log10(self) -> float:
        return float(sum(np.log10(np.prod(c.sizes())) for c in self.cells))


def load_spec(path: str | Path | None) -> dict[str, Any]:
    """The YAML search spec at ``path`` (an empty spec when None)."""
    if path is None:
        return {}
    from rflscm.config import load_yaml

    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"--search {path}: file not found; give a YAML search spec (see `rflscm optimize --help`).")
    spec = load_yaml(path) or {}
    if not isinstance(spec, dict):
        raise ConfigError(f"{path.name}: a search spec is a mapping with keys {', '.join(sorted(_TOP_KEYS))}.")
    return spec


def parse_range(text: str, option: str) -> dict[str, float]:
    """``"MIN:MAX:STEP"`` (or ``"MIN:MAX"``, step 1) from a CLI flag."""
    parts = text.split(":")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ConfigError(f"{option} takes MIN:MAX[:STEP] in degrees (got {text!r}).") from None
    if len(values) not in (2, 3):
        raise ConfigError(f"{option} takes MIN:MAX[:STEP] in degrees (got {text!r}).")
    return {
        "min": values[0],
        "max": values[1],
        "step": values[2] if len(values) == 3 else 1.0,
    }


def build_space(spec: dict[str, Any], cells: pd.DataFrame, codebooks: dict[str, Any]) -> SearchSpace:
    """Per-cell options from a spec mapping and the base round's cells table.

    Raises:
        ConfigError: unknown keys, cells or codebooks; a reversed or non-positive range; a space
            where no cell can change.
    """
    unknown = set(spec) - _TOP_KEYS
    if unknown:
        raise ConfigError(f"search spec: unknown key(s) {sorted(unknown)}; valid: {', '.join(sorted(_TOP_KEYS))}.")
    ids = cells["cell_id"].to_numpy()
    valid_ids = ", ".join(str(i) for i in ids)
    max_step = _max_step(spec.get("max_step"))
    defaults = _cell_spec(spec.get("defaults") or {}, "defaults")
    per_cell = spec.get("cells") or {}
    if not isinstance(per_cell, dict):
        raise ConfigError("search spec `cells` must map cell ids to option overrides.")
    overrides = {}
    for key, value in per_cell.items():
        overrides[_cell_id(key, ids, valid_ids, "cells")] = _cell_spec(value or {}, f"cells.{key}")
    frozen = {_cell_id(c, ids, valid_ids, "frozen") for c in (spec.get("frozen") or [])}
    # any codebook kind may serve SSB (docs/codebooks.md): `all` = the `type: ssb` books and those serving SSB now
    in_use = set(cells["ssb_codebook"].astype(str))
    ssb_books = [name for name, cb in codebooks.items() if getattr(cb, "type", None) == "ssb" or name in in_use]
    out = []
    for row in cells.itertuples(index=False):
        cell_id = int(row.cell_id)
        opts = {**defaults, **overrides.get(cell_id, {})}
        out.append(_cell_options(row, opts, ssb_books, cell_id in frozen, list(codebooks), max_step))
    max_changed = spec.get("max_changed_cells", DEFAULT_MAX_CHANGED)
    if max_changed is not None and (not isinstance(max_changed, int) or max_changed < 1):
        raise ConfigError(f"search spec `max_changed_cells` must be a whole number >= 1 or null (got {max_changed!r}).")
    space = SearchSpace(tuple(out), max_changed, max_step.get("total_tilt_deg"), panel_groups(cells))
    if not space.free_cells():
        raise ConfigError(
            "empty search space: every cell is frozen or has only its current value; unfreeze a cell or widen "
            "a range (e.g. --tilt-range 0:15:1)."
        )
    return space


def panel_groups(cells: pd.DataFrame) -> tuple[tuple[int, ...], ...]:
    """Positions of cells that share an antenna panel: the ``panel_id`` column where the cells table has
    one (empty = a panel of its own), else cells of one site with the same azimuth (to 0.1°)."""
    if "panel_id" in cells.columns:
        keys: list[tuple[object, ...] | None] = [
            None if pd.isna(v) or str(v).strip() == "" else ("panel", str(v)) for v in cells["panel_id"]
        ]
    else:
        keys = [("site", int(s), round(float(a) % 360.0, 1)) for s, a in zip(cells["site_id"], cells["azimuth_deg"])]
    groups: dict[Any, list[int]] = {}
    for pos, key in enumerate(keys):
        if key is not None:
            groups.setdefault(key, []).append(pos)
    return tuple(tuple(g) for g in groups.values() if len(g) > 1)


def _max_step(value: Any) -> dict[str, float | None]:
    """The per-step change limits: :data:`DEFAULT_MAX_STEP` with the spec's ``max_step`` laid over (null: none)."""
    if value is None:
        return dict(DEFAULT_MAX_STEP)
    if not isinstance(value, dict) or set(value) - set(DEFAULT_MAX_STEP):
        raise ConfigError(
            f"search spec `max_step` must map some of {', '.join(DEFAULT_MAX_STEP)} to degrees (got {value!r})."
        )
    out: dict[str, float | None] = dict(DEFAULT_MAX_STEP)
    for key, v in value.items():
        if v is not None and not (isinstance(v, (int, float)) and v > 0):
            raise ConfigError(f"search spec `max_step.{key}` must be a positive number of degrees or null (got {v!r}).")
        out[key] = None if v is None else float(v)
    return out


def _cell_id(value: Any, ids: np.ndarray, valid: str, where: str) -> int:
    try:
        cell = int(value)
    except (TypeError, ValueError):
        raise ConfigError(f"search spec `{where}`: {value!r} is not a cell id; cells: {valid}.") from None
    if cell not in ids:
        raise ConfigError(f"search spec `{where}`: unknown cell {cell}; cells of the scenario: {valid}.")
    return cell


def _cell_spec(spec: object, where: str) -> dict[str, Any]:
    if not isinstance(spec, dict):
        raise ConfigError(f"search spec `{where}` must be a mapping with keys {', '.join(sorted(_CELL_KEYS))}.")
    unknown = set(spec) - _CELL_KEYS
    if unknown:
        raise ConfigError(
            f"search spec `{where}`: unknown key(s) {sorted(unknown)}; valid: {', '.join(sorted(_CELL_KEYS))}."
        )
    out: dict[str, Any] = {}
    for key, value in spec.items():
        out[key] = value if key == "ssb_codebooks" else _range(value, f"{where}.{key}")
    return out


def _range(value: object, where: str) -> dict[str, float]:
    if not isinstance(value, dict) or not {"min", "max"} <= set(value) or set(value) - {"min", "max", "step"}:
        raise ConfigError(f"search spec `{where}` must be {{min: A, max: B, step: S}} in degrees (got {value!r}).")
    lo, hi, step = (
        float(value["min"]),
        float(value["max"]),
        float(value.get("step", 1.0)),
    )
    if lo > hi:
        raise ConfigError(f"search spec `{where}`: range reversed (min {lo:g} > max {hi:g}); swap the bounds.")
    if step <= 0:
        raise ConfigError(f"search spec `{where}`: step must be > 0 degrees (got {step:g}).")
    check_physical(where.rsplit(".", 1)[-1], lo, hi, where)
    return {"min": lo, "max": hi, "step": step}


_FLAGS = {
    "mech_tilt_deg": "--tilt-range",
    "elec_tilt_deg": "--elec-tilt-range",
    "azimuth_offset_deg": "--azimuth-range",
}


def check_physical(key: str, lo: float, hi: float, where: str) -> None:
    """Refuse a range beyond :data:`PHYSICAL_LIMITS` (a :class:`ConfigError` naming the limit)."""
    if key not in PHYSICAL_LIMITS:
        return
    a, b = PHYSICAL_LIMITS[key]
    if lo < a - 1e-9 or hi > b + 1e-9:
        what = {
            "mech_tilt_deg": "mechanical tilt",
            "elec_tilt_deg": "electrical tilt",
            "azimuth_offset_deg": "azimuth offset",
        }[key]
        raise ConfigError(
            f"{where} {lo:g}:{hi:g}: the {what} must stay within the physical limits {a:g}…{b:g} degrees "
            "(docs/optimize.md)."
        )


def _values(rng: dict[str, float], current: float) -> tuple[tuple[float, ...], int]:
    """Grid values of a range, with ``current`` added when absent; and the index of ``current``."""
    n = int(np.floor((rng["max"] - rng["min"]) / rng["step"] + 1e-9)) + 1
    values = np.round(rng["min"] + rng["step"] * np.arange(n), 6)
    values = np.unique(np.append(values, round(float(current), 6)))
    return tuple(float(v) for v in values), int(np.flatnonzero(values == round(float(current), 6))[0])


def _window(values: tuple[float, ...], current: float, step: float | None, circular: bool = False) -> tuple[float, ...]:
    """The values within ``step`` of ``current`` (all of them when ``step`` is None)."""
    if step is None:
        return values

    def dist(v: float) -> float:
        d = abs(v - current)
        return min(d, 360.0 - d) if circular else d

    return tuple(v for v in values if dist(v) <= step + 1e-9)


def _cell_options(
    row: Any,
    opts: dict[str, Any],
    ssb_books: list[str],
    frozen: bool,
    valid: list[str] | None = None,
    max_step: dict[str, float | None] | None = None,
) -> CellOptions:
    cell_id = int(row.cell_id)
    current_book = str(row.ssb_codebook)
    if frozen:
        values: dict[str, tuple[Any, ...]] = {
            "ssb_codebook": (current_book,),
            "elec_tilt_deg": (float(row.elec_tilt_deg),),
            "mech_tilt_deg": (float(row.mech_tilt_deg),),
            "azimuth_deg": (float(row.azimuth_deg),),
        }
        return CellOptions(cell_id, values, (0, 0, 0, 0))
    books = opts.get("ssb_codebooks", "all")
    if books in (None, "all"):
        books = list(ssb_books)
    if isinstance(books, str):
        books = [b.strip() for b in books.split(",") if b.strip()]
    valid = ssb_books if valid is None else valid
    for name in books:
        if name not in valid:
            raise ConfigError(
                f"search spec: cell {cell_id}: {name!r} is not a codebook of scenario.yaml; "
                f"codebooks: {', '.join(valid) or 'none'}."
            )
    books = [b for b in valid if b in books or b == current_book]
    elec, i_elec = _values(opts.get("elec_tilt_deg", DEFAULT_RANGES["elec_tilt_deg"]), row.elec_tilt_deg)
    mech, i_mech = _values(opts.get("mech_tilt_deg", DEFAULT_RANGES["mech_tilt_deg"]), row.mech_tilt_deg)
    offsets, i_az = _values(opts.get("azimuth_offset_deg", DEFAULT_RANGES["azimuth_offset_deg"]), 0.0)
    azimuths = tuple(float(np.round((row.azimuth_deg + o) % 360.0, 6)) for o in offsets)
    step = max_step or {}
    elec = _window(elec, float(row.elec_tilt_deg), step.get("elec_tilt_deg"))
    mech = _window(mech, float(row.mech_tilt_deg), step.get("mech_tilt_deg"))
    azimuths = _window(azimuths, float(np.round(row.azimuth_deg % 360.0, 6)), step.get("azimuth_deg"), circular=True)
    i_elec = elec.index(float(round(float(row.elec_tilt_deg), 6)))
    i_mech = mech.index(float(round(float(row.mech_tilt_deg), 6)))
    i_az = azimuths.index(float(np.round(row.azimuth_deg % 360.0, 6)))
    values = {
        "ssb_codebook": tuple(books),
        "elec_tilt_deg": elec,
        "mech_tilt_deg": mech,
        "azimuth_deg": azimuths,
    }
    return CellOptions(cell_id, values, (books.index(current_book), i_elec, i_mech, i_az))


def cells_table(base: pd.DataFrame, space: SearchSpace, config: list[tuple[int, ...]]) -> pd.DataFrame:
    """The base round's cells table with every cell set to ``config`` (one index tuple per cell)."""
    table = base.copy()
    for pos, (opts, index) in enumerate(zip(space.cells, config)):
        for var, value in opts.config(index).items():
            table.loc[table.index[pos], var] = value
    return table


def changes_table(base: pd.DataFrame, new: pd.DataFrame) -> pd.DataFrame:
    """Per-cell changes (only changed cells): before/after of every searched variable."""
    rows = []
    for (_, b), (_, n) in zip(base.iterrows(), new.iterrows()):
        if all(b[v] == n[v] for v in VARIABLES):
            continue
        row: dict[str, Any] = {
            "cell_id": int(b["cell_id"]),
            "site_id": int(b["site_id"]),
            "freq_hz": float(b["freq_hz"]),
        }
        for v in VARIABLES:
            row[f"{v}_before"], row[f"{v}_after"] = b[v], n[v]
        rows.append(row)
    columns = ["cell_id", "site_id", "freq_hz"] + [f"{v}_{w}" for v in VARIABLES for w in ("before", "after")]
    return pd.DataFrame(rows, columns=columns)
