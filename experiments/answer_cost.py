"""What RF-LSCM's answer costs at the pairs it does not render, against WNOMP's (issue 29).

    PYTHONPATH=src python experiments/answer_cost.py SCENARIO RFLSCM.ckpt WNOMP.ckpt [CELLS]

Takes the round-2 CSI-RS test pairs with round-1 reports of the first CELLS cells (default 20), and times, per model,
``predict_rsrp`` of them all and ``aps`` cell by cell (three runs each, after one warm-up call), then prints the
largest own times of a profile of RF-LSCM's ``aps`` (DECISIONS, "RF-LSCM's answer at the pairs it does not render
writes into its own tensor").
"""

import cProfile
import pstats
import sys
import time

import pandas as pd

from rflscm.data import load_scenario
from rflscm.data.measurements import reported_pairs
from rflscm.eval.protocols import AdjustProtocol
from rflscm.models import load_model
from rflscm.models.source import predict_rsrp

scenario = load_scenario(sys.argv[1])
rflscm, wnomp = (load_model(path, scenario) for path in sys.argv[2:4])
num_cells = int(sys.argv[4]) if len(sys.argv) > 4 else 20
protocol = AdjustProtocol()
pairs, _ = protocol.test_set(scenario).tables["csi"]
trained = pd.MultiIndex.from_frame(reported_pairs(protocol.training_scenario(scenario).measurements))
pairs = pairs[pd.MultiIndex.from_frame(pairs[["cell_id", "grid_id"]]).isin(trained)]
cells = pairs["cell_id"].unique()[:num_cells]
pairs = pairs[pairs["cell_id"].isin(cells)].reset_index(drop=True)
print(f"{len(pairs)} CSI-RS pairs with round-1 reports of {len(cells)} cells")


def answer_each_cell(model: object) -> None:
    for cell in cells:
        mine = pairs[pairs["cell_id"] == cell]
        model.aps(mine["cell_id"].to_numpy(), mine["grid_id"].to_numpy())  # type: ignore[attr-defined]


for name, model in (("wnomp", wnomp), ("rflscm", rflscm)):
    predict_rsrp(model, scenario, 2, "csi", pairs.iloc[:50])  # warm-up: sensing matrices, the renderer's setup
    begun = time.perf_counter()
    for _ in range(3):
        predict_rsrp(model, scenario, 2, "csi", pairs)
    predict_s = (time.perf_counter() - begun) / 3
    begun = time.perf_counter()
    for _ in range(3):
        answer_each_cell(model)
    print(f"{name}: predict_rsrp {predict_s:.2f} s, aps alone {(time.perf_counter() - begun) / 3:.2f} s")
profile = cProfile.Profile()
profile.runcall(answer_each_cell, rflscm)
pstats.Stats(profile).sort_stats("tottime").print_stats(10)
