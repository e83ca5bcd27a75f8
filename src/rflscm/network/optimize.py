"""``rflscm optimize`` as a library call: cache APS, search, KPIs before/after, truth check, new round."""

from __future__ import annotations

import dataclasses
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
import yaml

from rflscm.errors import ConfigError
from rflscm.eval.cache import load_or_render as load_or_cache_aps  # noqa: F401  (the CLI calls it here)
from rflscm.network.candidates import ApsCache
from rflscm.network.kpi import KPIConfig, network_kpis
from rflscm.network.search import (
    NetworkEvaluator,
    SearchResult,
    coordinate_descent,
    differential_evolution,
)
from rflscm.network.space import SearchSpace, cells_table, changes_table

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.network.verify import TruthVerifier

METHODS = ("cd", "de")
HOLDOUT_FRACTION = 0.2
"""Share of the grids the search never sees; the predicted gain on them checks the recommendation when there is
no truth (a gain that exists only on the searched grids is overfitting the model's errors)."""
KPI_KEYS = ("coverage", "mean_sinr_db", "p5_sinr_db", "overlap", "mean_rsrp_dbm", "no_signal")


def objective_gain(
    before: dict[str, float], after: dict[str, float], objective: str, sinr_weight: float = 0.1
) -> float:
    """The gain of the KPI an objective maximises: coverage [fraction], mean SS-SINR [dB] or their weighted sum."""
    d_cov = after["coverage"] - before["coverage"]
    d_sinr = after["mean_sinr_db"] - before["mean_sinr_db"]
    if objective == "coverage":
        return d_cov
    if objective == "sinr":
        return d_sinr
    return d_cov + sinr_weight * d_sinr / 10.0


def verdict(summary: dict[str, Any]) -> dict[str, Any]:
    """Whether to flag the recommendation: its true objective gain (when truth exists), else its predicted
    gain on held-out grids, is negative.  Returns ``{"flagged", "basis", "gain", "text"}``."""
    objective = summary["objective"]
    what = {"coverage": "coverage", "sinr": "mean SS-SINR", "weighted": "weighted coverage + SINR"}[objective]
    if summary.get("truth") is not None:
        basis, kpis = "true", summary["truth"]
    elif summary.get("held_out") is not None:
        basis, kpis = "held-out predicted", summary["held_out"]
    else:
        return {"flagged": False, "basis": None, "gain": None, "text": "no truth and no held-out grids to check on"}
    gain = objective_gain(kpis["before"], kpis["after"], objective)
    flagged = gain < -1e-9
    scale, unit = (100.0, " points") if objective == "coverage" else (1.0, " dB" if objective == "sinr" else "")
    text = f"the {basis} {what} gain is {gain * scale:+.2f}{unit}"
    if flagged:
        text = f"do not apply: {text}, although the search predicted an improvement"
    return {"flagged": flagged, "basis": basis, "gain": gain, "text": text}


@dataclass
class OptimizeResult:
    """Everything ``rflscm optimize`` reports."""

    model: str
    objective: str
    method: str
    search: SearchResult
    cells_before: pd.DataFrame
    cells_after: pd.DataFrame
    changes: pd.DataFrame
    predicted: dict[str, dict[str, Any]]
    """``before`` / ``after`` network KPIs on the model's APS."""
    power_before: np.ndarray
    power_after: np.ndarray
    """Predicted best-beam RSRP ``[num_cells, num_grids]`` [mW]."""
    known: np.ndarray | None
    """Pairs the KPIs were computed on (WNOMP: measured round-1 pairs); None = every pair."""
    timings: dict[str, float]
    truth: dict[str, Any] | None = None
    """True ``before`` / ``after`` KPIs on the same pairs as :attr:`predicted`."""
    truth_power: dict[str, np.ndarray] = field(default_factory=dict)
    truth_all: dict[str, Any] | None = None
    """True KPIs on every (cell, grid) pair, when :attr:`known` restricts the others (WNOMP)."""
    held_out: dict[str, Any] | None = None
    """Predicted ``before`` / ``after`` KPIs on the grids the search did not see."""
    held_out_grids: int = 0
    pairs_label: str = ""
    """Which pairs the KPIs cover, in words (the APS cache's :attr:`~rflscm.eval.cache.ScenarioAPS.pairs`)."""

    def summary(self) -> dict[str, Any]:
        """JSON-able summary (KPIs, gains, changes, timings, search statistics)."""
        keys = KPI_KEYS
        pairs = int(self.known.sum()) if self.known is not None else int(self.power_before.size)
        out: dict[str, Any] = {
            "model": self.model,
            "objective": self.objective,
            "method": self.search.method,
            "kpi_pairs": self.pairs_label
            or ("measured round-1 pairs only" if self.known is not None else "every (cell, grid) pair"),
            "kpi_pair_count": pairs,
            "predicted": self.predicted,
            "predicted_gain": {k: self.predicted["after"][k] - self.predicted["before"][k] for k in keys},
            "changed_cells": len(self.changes),
            "search": {
                "evaluations": self.search.evaluations,
                "time_s": self.search.time_s,
                "candidates_per_s": self.search.evaluations / max(self.search.time_s, 1e-9),
                "objective_before": self.search.base_objective,
                "objective_after": self.search.objective,
            },
            "timings_s": self.timings,
        }
        if self.held_out is not None:
            out["held_out"] = self.held_out
            out["held_out_gain"] = {k: self.held_out["after"][k] - self.held_out["before"][k] for k in keys}
        if self.truth is not None:
            out["truth"] = self.truth
            out["true_gain"] = {k: self.truth["after"][k] - self.truth["before"][k] for k in keys}
            out["level_gap"] = {k: self.predicted["before"][k] - self.truth["before"][k] for k in keys}
        if self.truth_all is not None:
            out["truth_all_pairs"] = self.truth_all
        out["verdict"] = verdict(out)
        return out


def run_optimize(
    scenario: Scenario,
    cache: ApsCache,
    space: SearchSpace,
    base_round: int = 1,
    objective: str = "coverage",
    method: str = "cd",
    kpi: KPIConfig | None = None,
    verify: bool | None = None,
    seed: int = 0,
    restarts: int = 2,
    time_budget_s: float = 60.0,
    sinr_weight: float = 0.1,
    on_step: Callable[[], None] | None = None,
    holdout_fraction: float | None = None,
) -> OptimizeResult:
    """Search ``space`` on the cached APS and report KPIs before and after (and on truth).

    Args:
        verify: True = compute true KPIs (a :class:`DataError` without ``truth/``); None = when
            ``truth/`` exists; False = never.
        method: ``cd`` (coordinate descent with restarts) or ``de`` (scipy differential evolution).
        on_step: called after every cell visit (cd) or generation (de), for progress bars.
        holdout_fraction: share of the grids (drawn with ``seed``) the search does not score; the
            predicted KPIs on them check the recommendation (:func:`verdict`).  None: :data:`HOLDOUT_FRACTION`
            without truth, 0 with truth (the true gain checks it, so the search may use every grid).

    Predicted and true KPIs cover the same pairs: the model's known pairs (every pair, or WNOMP's
    measured round-1 pairs); the true KPIs on every pair come beside them for WNOMP.
    """
    if method not in METHODS:
        raise ConfigError(f"--method must be one of {', '.join(METHODS)} (got {method!r}).")
    kpi = kpi or KPIConfig()
    truth_verifier = _verifier(scenario, verify)
    t0 = time.perf_counter()
    if holdout_fraction is None:
        holdout_fraction = 0.0 if truth_verifier is not None else HOLDOUT_FRACTION
    num_grids = len(cache.grid_ids)
    held = np.zeros(num_grids, dtype=bool)
    n_held = int(round(holdout_fraction * num_grids))
    if 0 < n_held < num_grids:
        held[np.random.default_rng(seed).permutation(num_grids)[:n_held]] = True
    known = None if cache.known.all() else cache.known
    ev = NetworkEvaluator(
        scenario, base_round, cache, space, kpi, objective, sinr_weight, grid_mask=~held if held.any() else None
    )
    power_before = ev.power.double().numpy().copy()
    if method == "cd":
        result = coordinate_descent(ev, restarts=restarts, seed=seed, on_cell=on_step)
    else:
        result = differential_evolution(ev, time_budget_s=time_budget_s, seed=seed, on_generation=on_step)
    power_after = ev.power.double().numpy().copy()
    timings = {"search_s": time.perf_counter() - t0}
    base = scenario.cells[base_round]
    after = cells_table(base, space, result.config)
    freqs = ev.freqs

    def kpis_on(power: np.ndarray, pairs: np.ndarray | None) -> dict[str, Any]:
        return network_kpis(power, freqs, kpi, pairs)

    predicted = {"before": kpis_on(power_before, known), "after": kpis_on(power_after, known)}
    out = OptimizeResult(
        cache.model,
        objective,
        method,
        result,
        base,
        after,
        changes_table(base, after),
        predicted,
        power_before,
        power_after,
        known,
        timings,
        pairs_label=cache.pairs,
    )
    if held.any():
        pairs_held = (cache.known if known is not None else np.ones_like(cache.known)) & held[None, :]
        if pairs_held.any():
            out.held_out = {"before": kpis_on(power_before, pairs_held), "after": kpis_on(power_after, pairs_held)}
            out.held_out_grids = int(held.sum())
    if truth_verifier is not None:
        t1 = time.perf_counter()
        out.truth_power = {
            "before": truth_verifier.best_power(base),
            "after": truth_verifier.best_power(after),
        }
        note = (
            "noiseless expectation from the traced paths (no noise, quantisation or reporting rule); "
            f"regime {truth_verifier.regime}"
        )
        out.truth = {
            "before": kpis_on(out.truth_power["before"], known),
            "after": kpis_on(out.truth_power["after"], known),
            "note": note + ("; on the same pairs as the predicted KPIs" if known is not None else "; every pair"),
        }
        if known is not None:
            out.truth_all = {
                "before": kpis_on(out.truth_power["before"], None),
                "after": kpis_on(out.truth_power["after"], None),
                "note": note + "; every (cell, grid) pair",
            }
        timings["verify_s"] = time.perf_counter() - t1
    return out


def _verifier(scenario: Scenario, verify: bool | None) -> TruthVerifier | None:
    from rflscm.network.verify import TruthVerifier

    if verify is False:
        return None
    has_truth = scenario.meta.truth is not None and (scenario.root / scenario.meta.truth).is_dir()
    if verify is None and not has_truth:
        return None
    return TruthVerifier(scenario)  # raises DataError without truth/


def write_round(scenario: Scenario, cells: pd.DataFrame, out_dir: Path) -> tuple[Path, int]:
    """Write ``out_dir/scenario/``: a copy of scenario.yaml with a new ``rounds:`` entry and its cells
    table; every other file stays where it is, named by a path relative to the new folder, so the copy
    loads, checks and predicts like the original (same fingerprint, the checkpoint still fits) and still
    does after the folder that holds both is moved or copied elsewhere.  Returns (folder, round)."""
    from rflscm.data import write_table

    folder = Path(out_dir) / "scenario"
    folder.mkdir(parents=True, exist_ok=True)
    rnd = max(scenario.rounds()) + 1
    meta = scenario.meta.to_dict()
    root = Path(scenario.root).resolve()
    here = folder.resolve()

    def rel(name: str) -> str:
        return Path(os.path.relpath(root / name, here)).as_posix()

    meta["rounds"] = {r: {"cells": rel(f["cells"])} for r, f in meta["rounds"].items()}
    meta["rounds"][rnd] = {"cells": f"cells_round{rnd}.parquet"}
    for key in ("grids", "measurements", "point_cloud", "truth"):
        if meta[key] is not None:
            meta[key] = rel(meta[key])
    meta["description"] = (meta.get("description") or "") + f" Round {rnd}: written by `rflscm optimize`."
    meta["allow_outside"] = True  # its tables are the original scenario's, outside this folder (rflscm.data.loader)
    cols = [c for c in cells.columns]
    write_table(cells[cols].reset_index(drop=True), folder / f"cells_round{rnd}.parquet")
    (folder / "scenario.yaml").write_text(
        yaml.safe_dump(_plain(meta), sort_keys=False, allow_unicode=True, default_flow_style=None)
    )
    return folder, rnd


def _plain(value: object) -> object:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def replace_cells(scenario: Scenario, rnd: int, cells: pd.DataFrame) -> Scenario:
    """``scenario`` with round ``rnd`` set to ``cells`` (in memory)."""
    new = dataclasses.replace(scenario, cells={**scenario.cells, rnd: cells.reset_index(drop=True)})
    new._elements.update(scenario._elements)
    return new
