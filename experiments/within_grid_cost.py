"""What within-grid variation costs the oracle (issue 12): round-2 MAE of the true APS through the nominal A′,
taken from the round-2 UE samples themselves (the model floor), from all traced points of the grid, and from the
round-1 samples (what a perfect per-grid fit of round 1 could know), beside the noise floor; with each oracle's
mean signed error (prediction − measurement), which shows the selection bias of top-N and detection reports.

    PYTHONPATH=src python experiments/within_grid_cost.py [SCENARIO]   # default: the shipped scenario

Prints one JSON object; needs a field-regime scenario (truth/aps_samples.parquet).
"""

from __future__ import annotations

import json
import sys

from rflscm.data import load_scenario
from rflscm.eval import run_evaluation
from rflscm.eval.oracle import OracleModel
from rflscm.eval.protocols import AdjustProtocol
from rflscm.geometry import AngleGrid
from rflscm.sim import default_scenario_path


def main(path: str | None = None) -> dict:
    scenario = load_scenario(path or default_scenario_path())
    out: dict = {"scenario": scenario.meta.name, "points_per_grid": scenario.meta.simulation.get("points_per_grid"),
                 "samples_per_grid": (scenario.meta.simulation.get("field") or {}).get("samples_per_grid")}  # fmt: skip
    for label, sample_round in (("round2_samples", 2), ("all_points", None), ("round1_samples", 1)):
        oracle = OracleModel.for_scenario(scenario, AngleGrid(), "cpu", sample_round=sample_round)
        metrics = run_evaluation(oracle, scenario, AdjustProtocol(), oracle=None).metrics
        out[label] = {"mae_db": metrics["mae_db"], "bias_db": metrics["bias_db"]}
        out["noise_floor"] = metrics["noise_floor_mae_db"]
    return out


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1] if len(sys.argv) > 1 else None), indent=1))
