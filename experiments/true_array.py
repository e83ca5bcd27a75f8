"""What the nominal array costs on round 2: the model floor's oracle and a model scored, or a model trained and scored,
with every sensing matrix built from the *true* arrays (issue 28, deliverable 2; DECISIONS, "The true arrays'
ceiling").

The field regime's truth passes each cell's beams through an array with per-element amplitude and phase errors, fixed
per cell and kept across the rounds; every model, and the model floor, use the nominal array.  A model that learnt the
errors from round 1 (self-calibration) could at best reach what a model given the true arrays reaches.  The errors
are not stored with a scenario; this script draws them again from the scenario's seed, in the generator's order
(``(seed, 12)``: the UE samples first, then one array per cell in cell order; the samples drawn here are checked
against ``truth/samples.parquet``, so a scenario made another way is refused rather than scored with wrong arrays).

Usage (from the repository root, one thread):

    PYTHONPATH=src python experiments/true_array.py score SCENARIO [CHECKPOINT]

prints the oracle's (and the checkpoint's) round-2 MAE, the ``seen`` block, with the nominal and with the true arrays
(``NOMINAL`` / ``TRUE`` lines);

    PYTHONPATH=src python experiments/true_array.py cli SCENARIO RFLSCM-ARGS...

runs ``rflscm RFLSCM-ARGS`` with the true arrays in every sensing matrix (e.g. ``--threads 1 train SCENARIO --minutes
10 --out A.ckpt``, then ``--threads 1 evaluate A.ckpt SCENARIO --json A.json``).
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pandas as pd
import torch

from rflscm.antenna import sensing_matrix
from rflscm.data import load_scenario
from rflscm.data import scenario as scenario_module
from rflscm.data.scenario import Scenario
from rflscm.sim.field import FieldConfig, array_errors, draw_samples


def true_gains(scenario: Scenario) -> dict[int, torch.Tensor | None]:
    """Each cell's complex element gains ``[num_h, num_v]`` as the field regime drew them (None: no errors)."""
    sim = scenario.meta.simulation or {}
    if "field" not in sim or "config" not in sim:
        raise SystemExit("the scenario was not simulated in the field regime: its arrays are the nominal ones")
    config, setup = FieldConfig(**sim["field"]), sim["config"]
    rng = np.random.default_rng([int(setup["seed"]), 12])
    samples = draw_samples(
        np.asarray(scenario.grid_ids()), int(setup["points_per_grid"]), config, scenario.rounds(), rng
    )
    truth = pd.read_parquet(scenario.root / "truth" / "samples.parquet")
    if len(truth) != len(samples) or not np.array_equal(truth["point_id"].to_numpy(), samples["point_id"].to_numpy()):
        raise SystemExit("the scenario's UE samples are not the seed's draw: its arrays cannot be drawn again")
    gains = {}
    for cell_id in scenario.cell_ids():
        array = scenario.antenna(int(cell_id), 1).array
        gains[int(cell_id)] = array_errors(array.num_h, array.num_v, config, rng)
    return gains


def use_true_arrays(gains: dict[int, torch.Tensor | None]) -> None:
    """Every :meth:`Scenario.sensing` from now on passes the cell's true element gains (the method notes which cell
    it is building for; the sensing function it calls adds that cell's gains)."""
    cells: list[int] = []
    nominal = Scenario.sensing

    def sensing(self, cell_id, *args, **kwargs):
        cells.append(int(cell_id))
        try:
            return nominal(self, cell_id, *args, **kwargs)
        finally:
            cells.pop()

    def with_gains(*args, **kwargs):
        return sensing_matrix(*args, element_gains=gains[cells[-1]], **kwargs)

    scenario_module.sensing_matrix = with_gains
    Scenario.sensing = sensing


def score(scenario_dir: str, checkpoint: str | None) -> None:
    from rflscm.eval import AdjustProtocol, run_evaluation
    from rflscm.eval.oracle import OracleModel
    from rflscm.geometry.grid import AngleGrid
    from rflscm.models import load_model

    torch.set_num_threads(1)
    scenario = load_scenario(scenario_dir)
    gains = true_gains(scenario)
    model = load_model(checkpoint, scenario, device="cpu") if checkpoint else None
    oracle = OracleModel.for_scenario(scenario, model.angle_grid if model else AngleGrid(), "cpu", sample_round=2)
    for label in ("NOMINAL", "TRUE"):
        if label == "TRUE":
            use_true_arrays(gains)
        for name, source in (("oracle", oracle), ("model", model)):
            if source is None:
                continue
            mae = run_evaluation(source, scenario, AdjustProtocol(), oracle=None).metrics["seen"]["mae_db"]
            row = {bt: {k: round(float(v), 3) for k, v in mae[bt].items()} for bt in mae}
            print(label, name, json.dumps(row), flush=True)


if __name__ == "__main__":
    mode, scenario_dir = sys.argv[1], sys.argv[2]
    if mode == "score":
        score(scenario_dir, sys.argv[3] if len(sys.argv) > 3 else None)
    elif mode == "cli":
        use_true_arrays(true_gains(load_scenario(scenario_dir)))
        from rflscm.cli import main

        sys.argv = ["rflscm", *sys.argv[3:]]
        main()
    else:
        raise SystemExit(f"unknown mode {mode!r} (score, cli)")
