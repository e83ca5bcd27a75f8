"""``rflscm optimize`` as a library call: cache APS, search, KPIs before/after, truth check, new round."""

from __future__ import annotations

import dataclasses
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
from rflscm.network.kpi import KPIConfig
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
    truth_power: dict[str, np.ndarray] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """JSON-able summary (KPIs, gains, changes, timings, search statistics)."""
        keys = ("coverage", "mean_sinr_db", "p5_sinr_db", "overlap", "mean_rsrp_dbm")
        out: dict[str, Any] = {
            "model": self.model, "objective": self.objective, "method": self.search.method,
            "kpi_pairs": "measured round-1 pairs only" if self.known is not None else "every (cell, grid) pair",
            "predicted": self.predicted,
            "predicted_gain": {k: self.predicted["after"][k] - self.predicted["before"][k] for k in keys},
            "changed_cells": len(self.changes),
            "search": {"evaluations": self.search.evaluations, "time_s": self.search.time_s,
                       "candidates_per_s": self.search.evaluations / max(self.search.time_s, 1e-9),
                       "objective_before": self.search.base_objective, "objective_after": self.search.objective},
            "timings_s": self.timings,
        }  # fmt: skip
        if self.truth is not None:
            out["truth"] = self.truth
            out["true_gain"] = {k: self.truth["after"][k] - self.truth["before"][k] for k in keys}
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
) -> OptimizeResult:
    """Search ``space`` on the cached APS and report KPIs before and after (and on truth).

    Args:
        verify: True = compute true KPIs (a :class:`DataError` without ``truth/``); None = when
            ``truth/`` exists; False = never.
        method: ``cd`` (coordinate descent with restarts) or ``de`` (scipy differential evolution).
        on_step: called after every cell visit (cd) or generation (de), for progress bars.
    """
    if method not in METHODS:
        raise ConfigError(f"--method must be one of {', '.join(METHODS)} (got {method!r}).")
    kpi = kpi or KPIConfig()
    truth_verifier = _verifier(scenario, verify)
    t0 = time.perf_counter()
    ev = NetworkEvaluator(scenario, base_round, cache, space, kpi, objective, sinr_weight)
    before_kpis, power_before = ev.kpis(), ev.power.double().numpy().copy()
    if method == "cd":
        result = coordinate_descent(ev, restarts=restarts, seed=seed, on_cell=on_step)
    else:
        result = differential_evolution(ev, time_budget_s=time_budget_s, seed=seed, on_generation=on_step)
    after_kpis, power_after = ev.kpis(), ev.power.double().numpy().copy()
    timings = {"search_s": time.perf_counter() - t0}
    base = scenario.cells[base_round]
    after = cells_table(base, space, result.config)
    known = None if cache.known.all() else cache.known
    out = OptimizeResult(cache.model, objective, method, result, base, after, changes_table(base, after),
                         {"before": before_kpis, "after": after_kpis}, power_before, power_after, known,
                         timings)  # fmt: skip
    if truth_verifier is not None:
        t1 = time.perf_counter()
        out.truth_power = {
            "before": truth_verifier.best_power(base),
            "after": truth_verifier.best_power(after),
        }
        freqs = base["freq_hz"].to_numpy()
        from rflscm.network.kpi import network_kpis

        out.truth = {
            "before": network_kpis(out.truth_power["before"], freqs, kpi),
            "after": network_kpis(out.truth_power["after"], freqs, kpi),
            "note": "noiseless expectation from the traced paths (no noise, quantisation or reporting rule), "
            f"every (cell, grid) pair; regime {truth_verifier.regime}",
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
    table; every other file stays where it is (absolute references), so the copy loads, checks and
    predicts like the original (same fingerprint, the checkpoint still fits).  Returns (folder, round)."""
    from rflscm.data import write_table

    folder = Path(out_dir) / "scenario"
    folder.mkdir(parents=True, exist_ok=True)
    rnd = max(scenario.rounds()) + 1
    meta = scenario.meta.to_dict()
    root = Path(scenario.root).resolve()
    meta["rounds"] = {r: {"cells": str(root / f["cells"])} for r, f in meta["rounds"].items()}
    meta["rounds"][rnd] = {"cells": f"cells_round{rnd}.parquet"}
    for key in ("grids", "measurements", "point_cloud", "truth"):
        if meta[key] is not None:
            meta[key] = str(root / meta[key])
    meta["description"] = (meta.get("description") or "") + f" Round {rnd}: written by `rflscm optimize`."
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
