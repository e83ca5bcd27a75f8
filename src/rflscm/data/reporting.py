"""The reporting rule of a scenario and the upper bound it implies for every missing beam (SPEC §2, §3).

A beam is *missing* (NaN) because the rule left it out.  ``scenario.yaml`` declares the rule per beam
type under ``reporting:``::

    reporting:
      ssb: {rule: sinr, detection_db: -6.0, noise_dbm: -120.2}   # SS-SINR detection (+ optional top_n)
      csi: {rule: top_n, top_n: 4, serving_only: true}          # L1-RSRP: top 4 beams, serving cell only

A beam type without an entry (and every scenario without ``reporting:``) uses the absolute threshold
``rsrp_threshold_dbm``.  What each rule says about a missing beam of one *report* (the beams of one
(round, cell, grid, beam type)):

* ``threshold``: below r_th;
* ``top_n``: below the weakest reported beam of that report when the report is full (N beams), else
  below r_th (fewer than N beams cleared the threshold);
* ``sinr``: its SS-SINR was below ``detection_db``, i.e. its RSRP below the detection level
  γ + 10 log10(I + N), I the power of the other cells' same-index SSB beams on that carrier in that
  grid (synchronised SSB bursts collide index by index, TS 38.213 §4.1) as *reported* in the same
  round, N the noise per resource element; with ``top_n`` also, the larger of that level and the
  top-N bound (a beam may be missing for either reason).

Every bound is at least r_th.  :func:`missing_bounds` returns them aligned with
:meth:`Scenario.rsrp_table`, so that the training loss, evaluation and the trivial baseline share one
definition.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from rflscm.errors import ConfigError, DataError

BEAM_TYPES = ("ssb", "csi")
"""The two beam types of a scenario, in the order every table and report uses: SSB, then CSI-RS."""

RULES = ("threshold", "top_n", "sinr")


@dataclass(frozen=True)
class ReportingRule:
    """How the beams of one beam type were reported (one entry of ``scenario.yaml`` ``reporting:``)."""

    rule: str = "threshold"
    """``threshold``, ``top_n`` or ``sinr`` (see the module docstring)."""
    top_n: int | None = None
    """At most this many beams per report (required by ``top_n``, optional with ``sinr``)."""
    detection_db: float | None = None
    """SS-SINR detection level γ [dB] (``sinr`` only)."""
    noise_dbm: float | None = None
    """Noise power per resource element N [dBm] in the SS-SINR (``sinr`` only)."""
    serving_only: bool = False
    """Rows exist only for one serving cell per (round, grid, carrier) (UE-specific CSI-RS)."""

    def __post_init__(self) -> None:
        if self.rule not in RULES:
            raise ConfigError(f"`rule` = {self.rule!r} is not a reporting rule; allowed: {', '.join(RULES)}.")
        if self.top_n is not None and (isinstance(self.top_n, bool) or int(self.top_n) != self.top_n or self.top_n < 1):
            raise ConfigError(f"`top_n` must be a whole number >= 1 (got {self.top_n!r}).")
        if self.rule == "top_n" and self.top_n is None:
            raise ConfigError("rule `top_n` needs `top_n` (the most beams a report carries, e.g. 4).")
        if self.rule == "sinr" and (self.detection_db is None or self.noise_dbm is None):
            raise ConfigError("rule `sinr` needs `detection_db` (e.g. -6.0) and `noise_dbm` (e.g. -120.2).")
        if self.rule != "sinr" and (self.detection_db is not None or self.noise_dbm is not None):
            raise ConfigError(f"`detection_db` / `noise_dbm` belong to rule `sinr`, not {self.rule!r}.")

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"rule": self.rule}
        for key in ("top_n", "detection_db", "noise_dbm"):
            if getattr(self, key) is not None:
                out[key] = getattr(self, key)
        if self.serving_only:
            out["serving_only"] = True
        return out


def reporting_from_dict(value: object) -> dict[str, ReportingRule]:
    """Validate ``scenario.yaml`` ``reporting:`` (``None`` → threshold for every beam type)."""
    if value in (None, {}):
        return {}
    if not isinstance(value, dict):
        raise ConfigError(f"`reporting` must map beam types (ssb, csi) to rules (got {value!r}).")
    fields = ("rule", "top_n", "detection_db", "noise_dbm", "serving_only")
    out = {}
    for beam_type, spec in value.items():
        if beam_type not in BEAM_TYPES:
            raise ConfigError(f"`reporting` keys must be ssb or csi (got {beam_type!r}).")
        if not isinstance(spec, dict):
            raise ConfigError(f"`reporting.{beam_type}` must be a mapping, e.g. {{rule: top_n, top_n: 4}}.")
        unknown = sorted(set(spec) - set(fields))
        if unknown:
            raise ConfigError(f"`reporting.{beam_type}`: unknown key(s) {unknown}; valid keys: {', '.join(fields)}.")
        try:
            rule = ReportingRule(
                rule=str(spec.get("rule", "threshold")),
                top_n=None if spec.get("top_n") is None else int(spec["top_n"]),
                detection_db=None if spec.get("detection_db") is None else float(spec["detection_db"]),
                noise_dbm=None if spec.get("noise_dbm") is None else float(spec["noise_dbm"]),
                serving_only=bool(spec.get("serving_only", False)),
            )
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"`reporting.{beam_type}`: {exc}") from None
        except ConfigError as exc:
            raise ConfigError(f"`reporting.{beam_type}`: {exc}") from None
        if rule.rule == "sinr" and beam_type != "ssb":
            raise ConfigError("`reporting.csi`: rule `sinr` is SSB detection; use threshold or top_n for CSI-RS.")
        out[beam_type] = rule
    return out


def rule_of(scenario, beam_type: str) -> ReportingRule:
    """The scenario's rule for ``beam_type`` (``threshold`` when none is declared)."""
    return getattr(scenario.meta, "reporting", {}).get(beam_type, ReportingRule())


def missing_bounds(
    scenario, round: int, beam_type: str, pairs: pd.DataFrame | None = None, rsrp_dbm: np.ndarray | None = None
) -> np.ndarray:
    """Upper bound [dBm] of every missing beam, ``[num_pairs, max_beams]`` like ``rsrp_dbm``.

    Args:
        scenario: a :class:`~rflscm.data.Scenario`.
        round, beam_type: the report's round and beam type.
        pairs, rsrp_dbm: the round's wide table (default: :meth:`Scenario.rsrp_table`); under rule
            ``sinr`` the interference comes from the round's full SSB table regardless.

    Returns:
        float64 ``[num_pairs, max_beams]``: the bound where the beam is missing, NaN where it is
        reported or beyond the cell's codebook.
    """
    if pairs is None or rsrp_dbm is None:
        pairs, rsrp_dbm = scenario.rsrp_table(round, beam_type)
    rule = rule_of(scenario, beam_type)
    r_th = float(scenario.meta.rsrp_threshold_dbm)
    bound = np.full(rsrp_dbm.shape, r_th)
    if rule.rule == "sinr":
        bound = np.maximum(bound, _detection_level(scenario, round, pairs, rule, rsrp_dbm.shape[1]))
    if rule.top_n is not None:
        reported = ~np.isnan(rsrp_dbm)
        full = reported.sum(axis=1) >= rule.top_n
        weakest = np.where(reported, rsrp_dbm, np.inf).min(axis=1)
        bound = np.where(full[:, None], np.maximum(bound, weakest[:, None]), bound)
    cells, at = np.unique(pairs["cell_id"].to_numpy(), return_inverse=True)  # one codebook lookup per cell
    sizes = np.array([scenario.num_beams(int(c), beam_type, round) for c in cells], dtype=int)[at.reshape(-1)]
    exists = np.arange(rsrp_dbm.shape[1])[None, :] < sizes.reshape(-1, 1)
    return np.where(exists & np.isnan(rsrp_dbm), bound, np.nan)


def _detection_level(scenario, round: int, pairs: pd.DataFrame, rule: ReportingRule, width: int) -> np.ndarray:
    """γ + 10 log10(I + N) [dBm] ``[num_pairs, width]``, I from the round's reported SSB of the other cells
    on the pair's carrier in its grid, beam index by beam index."""
    ssb_pairs, ssb = scenario.rsrp_table(round, "ssb")
    freq = scenario.cells[1].set_index("cell_id")["freq_hz"]
    lin = np.nan_to_num(10.0 ** (ssb / 10.0), nan=0.0)  # [Q, M_ssb] mW
    lin = np.pad(lin, ((0, 0), (0, max(width - lin.shape[1], 0))))[:, :width]
    key_q = pd.MultiIndex.from_arrays([ssb_pairs["grid_id"].to_numpy(), freq.loc[ssb_pairs["cell_id"]].to_numpy()])
    totals = pd.DataFrame(lin).groupby(key_q.to_flat_index()).sum()
    key_p = pd.MultiIndex.from_arrays([pairs["grid_id"].to_numpy(), freq.loc[pairs["cell_id"]].to_numpy()])
    total = totals.reindex(key_p.to_flat_index()).fillna(0.0).to_numpy()  # [P, width]
    total = total + _outside_interference(scenario, round, key_p, width)
    own = pd.DataFrame(lin, index=pd.MultiIndex.from_frame(ssb_pairs[["cell_id", "grid_id"]]))
    own = own.reindex(pd.MultiIndex.from_frame(pairs[["cell_id", "grid_id"]])).fillna(0.0).to_numpy()
    assert rule.noise_dbm is not None  # checked by ReportingRule for rule `sinr`
    interference = np.maximum(total - own, 0.0) + 10.0 ** (rule.noise_dbm / 10.0)
    return rule.detection_db + 10.0 * np.log10(interference)


def _outside_interference(scenario, round: int, key_p: pd.MultiIndex, width: int) -> np.ndarray:
    """``[P, width]`` mW of reported SSB from cells cut away from the scenario (``Scenario.outside_ssb``) at each
    pair's (grid, carrier), beam index by beam index; zeros for a scenario loaded whole."""
    outside = getattr(scenario, "outside_ssb", None)
    if outside is None or len(outside) == 0:
        return np.zeros((len(key_p), width))
    rows = outside[(outside["round"] == round).to_numpy() & (outside["beam_id"] < width).to_numpy()]
    lin = pd.Series(10.0 ** (rows["rsrp_dbm"].to_numpy(np.float64) / 10.0))
    keys = [rows["grid_id"].to_numpy(), rows["freq_hz"].to_numpy(), rows["beam_id"].to_numpy()]
    wide = lin.groupby(keys).sum().unstack(fill_value=0.0).reindex(columns=range(width), fill_value=0.0)
    wide.index = wide.index.to_flat_index()
    return wide.reindex(key_p.to_flat_index()).fillna(0.0).to_numpy()


def check_reporting(scenario) -> list[str]:
    """Where the measurements break the declared rule (empty when they follow it).

    Checks per round: no report carries more than ``top_n`` beams; with ``serving_only``, rows of at
    most one cell per (grid, carrier); no reported value below r_th.
    """
    problems: list[str] = []
    m = scenario.measurements
    if len(m) == 0:
        return problems
    freq = scenario.cells[1].set_index("cell_id")["freq_hz"]
    for beam_type, rule in getattr(scenario.meta, "reporting", {}).items():
        rows = m[(m["beam_type"] == beam_type).to_numpy()]
        if rule.top_n is not None:
            counts = rows["rsrp_dbm"].notna().groupby([rows["round"], rows["cell_id"], rows["grid_id"]]).sum()
            worst = int(counts.max()) if len(counts) else 0
            if worst > rule.top_n:
                where = counts.idxmax()
                problems.append(
                    f"{beam_type}: report (round {where[0]}, cell {where[1]}, grid {where[2]}) carries {worst} beams, "
                    f"more than `reporting.{beam_type}.top_n` = {rule.top_n}."
                )
        if rule.serving_only and len(rows):
            cells = rows[["round", "grid_id", "cell_id"]].drop_duplicates()
            cells = cells.assign(freq=freq.loc[cells["cell_id"]].to_numpy())
            many = cells.groupby(["round", "grid_id", "freq"]).size()
            if (many > 1).any():
                where = many.idxmax()
                problems.append(
                    f"{beam_type}: round {where[0]}, grid {where[1]} has rows of {int(many.max())} cells on "
                    f"{where[2] / 1e9:g} GHz, but `reporting.{beam_type}.serving_only` allows only the serving cell."
                )
    below = m["rsrp_dbm"].to_numpy() < scenario.meta.rsrp_threshold_dbm
    if below.any():
        problems.append(f"{int(below.sum())} reported value(s) lie below rsrp_threshold_dbm.")
    return problems


def validate_reporting(scenario) -> None:
    """Raise :class:`DataError` naming the first way the measurements break the declared rule."""
    problems = check_reporting(scenario)
    if problems:
        raise DataError(f"measurements break the reporting rule of scenario.yaml: {problems[0]}")


def reported_fraction(scenario) -> pd.DataFrame:
    """Reported fraction of beams per (round, beam type): reported rows / (pairs × codebook size).

    Counts every beam of every (cell, grid) pair present in that round (at least one row of any beam
    type), so serving-only CSI-RS shows as the small fraction it is.
    """
    m = scenario.measurements
    out = []
    cell_ids, grid_ids = scenario.cell_ids(), scenario.grid_ids()
    rounds = m["round"].to_numpy()
    reported_rows = m["rsrp_dbm"].notna().to_numpy()
    of_type = {bt: (m["beam_type"] == bt).to_numpy() for bt in BEAM_TYPES} if len(m) else {}
    for rnd in sorted(np.unique(rounds)) if len(m) else []:
        sel = rounds == rnd
        c = np.searchsorted(cell_ids, m["cell_id"].to_numpy()[sel])
        g = np.searchsorted(grid_ids, m["grid_id"].to_numpy()[sel])
        pair_cells = np.unique(c * len(grid_ids) + g) // len(grid_ids)  # one entry per (cell, grid) pair
        pairs_per_cell = np.bincount(pair_cells, minlength=len(cell_ids))
        del c, g, pair_cells
        table = scenario.cells[int(rnd)]  # sorted by cell_id, the same ids as round 1
        for beam_type in BEAM_TYPES:
            beams = table[f"{beam_type}_codebook"].map(lambda name: scenario.meta.codebooks[name].num_beams)
            possible = int((pairs_per_cell * beams.to_numpy(dtype=np.int64)).sum())
            reported = int((sel & of_type[beam_type] & reported_rows).sum())
            out.append(
                {
                    "round": int(rnd),
                    "beam_type": beam_type,
                    "reported": reported,
                    "possible": int(possible),
                    "fraction": reported / possible if possible else float("nan"),
                }
            )
    return pd.DataFrame(out, columns=["round", "beam_type", "reported", "possible", "fraction"])
