"""Choosing WNOMP's settings as a practitioner would: on held-aside round-1 beams, never on round 2 (issue 12).

A share of the round-1 reports (``fraction`` of the (cell, grid, beam type) reports with at least two
reported beams, at most :data:`MAX_HELD`) each lose one reported beam, drawn at random; every candidate setting is
fitted on the rest and scored by its MAE on the hidden beams (SSB and CSI-RS pooled).  WNOMP fits each (cell, grid)
pair alone, so only the pairs with a hidden beam are fitted: the selection's cost is bounded at any network size.
The winner is refitted by the caller on all round-1 data.  Nothing here reads round 2 or ``truth/``.
"""

from __future__ import annotations

import dataclasses
import itertools
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import pandas as pd

from rflscm.data.scenario import SensingCache
from rflscm.geometry import AngleGrid
from rflscm.models.wnomp import WNOMPConfig, WNOMPModel

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario

CANDIDATES: dict[str, tuple[Any, ...]] = {
    "k_max": (2, 4, 8),
    "weighting": ("inverse_rsrp", "none"),
    "stopping": ("tolerance 0.01", "tolerance 0.05 + residual floor 0.25"),
}
"""The grid searched: atoms, weights, and two stopping rules (the default; an earlier stop that leaves ~1 dB of
residual, i.e. does not fit the noise)."""
STOPPING: dict[str, dict[str, Any]] = {
    "tolerance 0.01": {"tolerance": 0.01, "residual_floor": 0.0},
    "tolerance 0.05 + residual floor 0.25": {"tolerance": 0.05, "residual_floor": 0.25},
}


MAX_HELD = 10_000
"""The most beams held aside.  The candidates are ranked by their mean error on the same beams, whose spread is
about 2 dB a beam, so 10 000 beams pin each mean to about 0.02 dB, below the gaps between candidates.  On a large
network (the demo's 114-cell city holds 38 k reports to hide a beam of) it bounds the cost: the 12 candidates
were fitted on every pair, two minutes of a 4-minute demo there."""


def hold_aside(
    measurements: pd.DataFrame, fraction: float, seed: int, max_held: int = MAX_HELD
) -> tuple[pd.DataFrame, np.ndarray]:
    """``(training table, held-aside row positions)``: one reported round-1 beam hidden (NaN) in ``fraction``
    of the round-1 reports that carry at least two reported beams, at most ``max_held`` of them (a seeded draw
    among those picked)."""
    rng = np.random.default_rng(seed)
    m = measurements.reset_index(drop=True)
    reported = ((m["round"] == 1) & m["rsrp_dbm"].notna()).to_numpy()
    rows = m[reported]
    counts = rows.groupby(["cell_id", "grid_id", "beam_type"])["rsrp_dbm"].transform("size").to_numpy()
    eligible = rows[counts >= 2]
    reports = eligible.groupby(["cell_id", "grid_id", "beam_type"]).indices
    picked = []
    for positions in reports.values():
        if rng.random() < fraction:
            picked.append(int(eligible.index[positions[rng.integers(len(positions))]]))
    held = np.asarray(picked, dtype=np.int64)
    if len(held) > max_held:
        held = rng.choice(held, size=max_held, replace=False)
    held = np.sort(held)
    train = m.copy()
    train.loc[held, "rsrp_dbm"] = np.nan
    return train, held


def candidate_configs(base: WNOMPConfig | None = None) -> list[tuple[dict[str, Any], WNOMPConfig]]:
    """Every setting of :data:`CANDIDATES` as ``(label dict, config)``."""
    base = base or WNOMPConfig()
    out = []
    for k_max, weighting, stopping in itertools.product(*CANDIDATES.values()):
        cfg = dataclasses.replace(base, k_max=k_max, weighting=weighting, **STOPPING[stopping])
        out.append(({"k_max": k_max, "weighting": weighting, "stopping": stopping}, cfg))
    return out


def select_wnomp(
    scenario: Scenario,
    angle_grid: AngleGrid,
    fraction: float = 0.2,
    seed: int = 0,
    device: str = "cpu",
    base: WNOMPConfig | None = None,
) -> tuple[WNOMPConfig, pd.DataFrame]:
    """The candidate with the lowest MAE on held-aside round-1 beams, and the table of every candidate
    (``k_max``, ``weighting``, ``stopping``, ``mae_ssb_db``, ``mae_csi_db``, ``mae_db`` pooled, ``beams``)."""
    train_table, held = hold_aside(scenario.measurements, fraction, seed)
    truth = scenario.measurements.reset_index(drop=True).iloc[held]
    # the candidates share the cells' sensing matrices (a third of the selection's time when each computed its own)
    train = cast(
        "Scenario", SensingCache(scenario.with_measurements(_pairs_of(train_table, truth), validate=False), None)
    )
    rows = []
    for label, cfg in candidate_configs(base):
        model = WNOMPModel(cfg, angle_grid, device)
        model.fit(train, progress=False)
        errors = {t: _held_errors(model, train, truth[truth["beam_type"] == t], t) for t in ("ssb", "csi")}
        pooled = np.concatenate(list(errors.values()))
        rows.append(
            {
                **label,
                "mae_ssb_db": _mean(errors["ssb"]),
                "mae_csi_db": _mean(errors["csi"]),
                "mae_db": _mean(pooled),
                "beams": int(pooled.size),
            }
        )
    table = pd.DataFrame(rows)
    best = int(table["mae_db"].fillna(np.inf).to_numpy().argmin())
    return candidate_configs(base)[best][1], table


def _pairs_of(table: pd.DataFrame, held: pd.DataFrame) -> pd.DataFrame:
    """The rows of ``table`` at the (cell, grid) pairs of ``held``: all a per-pair fit needs to predict them."""
    wanted = pd.MultiIndex.from_frame(held[["cell_id", "grid_id"]].drop_duplicates())
    return table[pd.MultiIndex.from_frame(table[["cell_id", "grid_id"]]).isin(wanted)].reset_index(drop=True)


def _held_errors(model: WNOMPModel, scenario: Scenario, held: pd.DataFrame, beam_type: str) -> np.ndarray:
    """|prediction − measurement| [dB] of the held-aside beams of one type (pairs the model never saw drop out)."""
    if len(held) == 0:
        return np.zeros(0)
    pairs = held[["cell_id", "grid_id"]].drop_duplicates().reset_index(drop=True)
    pred = model.predict_rsrp(scenario, 1, beam_type, pairs)  # [P, M] dBm
    row = pd.MultiIndex.from_frame(pairs).get_indexer(pd.MultiIndex.from_frame(held[["cell_id", "grid_id"]]))
    err = np.abs(pred[row, held["beam_id"].to_numpy()] - held["rsrp_dbm"].to_numpy())
    return err[np.isfinite(err)]


def _mean(values: np.ndarray) -> float | None:
    return float(values.mean()) if values.size else None
