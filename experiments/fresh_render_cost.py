"""What a render costs per pair at the test pairs without a round-1 report against training pairs (issue 29).

    PYTHONPATH=src python experiments/fresh_render_cost.py SCENARIO CHECKPOINT

Loads an RF-LSCM checkpoint and times its renderer (each `renderer.output` call, with the pairs and cells of its
chunk) through `model.aps` on the round-2 pairs that round 1 did not report (the ones an evaluation always renders),
then on as many round-1 pairs drawn at random with the kept renders and WNOMP's fallback switched off, so that they
are rendered too (DECISIONS, "The pass keeps its renders": why the 222-cell ideal demo's evaluation ran over).
"""

import sys
import time

import numpy as np
import torch

from rflscm.data import load_scenario
from rflscm.models import load_model

scenario = load_scenario(sys.argv[1])
model = load_model(sys.argv[2], scenario, device="cpu")
renderer = model.renderer
calls = []
output = renderer.output


def timed(cells, xyz, position):
    t0 = time.perf_counter()
    out = output(cells, xyz, position)
    calls.append((len(cells), int(torch.unique(cells).numel()), time.perf_counter() - t0))
    return out


renderer.output = timed
m = scenario.measurements
round1 = m[m["round"] == 1][["cell_id", "grid_id"]].drop_duplicates()
round2 = m[m["round"] == 2][["cell_id", "grid_id"]].drop_duplicates()
both = round2.merge(round1, how="left", indicator=True)
fresh = both[both["_merge"] == "left_only"]


def run(pairs, name):
    calls.clear()
    t0 = time.perf_counter()
    model.aps(pairs["cell_id"].to_numpy(), pairs["grid_id"].to_numpy())
    total = time.perf_counter() - t0
    n = sum(c[0] for c in calls)
    render = sum(c[2] for c in calls)
    cells = np.mean([c[1] for c in calls]) if calls else 0.0
    print(
        f"{name}: {len(pairs)} asked, {n} rendered in {len(calls)} chunks ({cells:.1f} cells a chunk), "
        f"{render:.1f} s = {1e3 * render / max(n, 1):.1f} ms a pair; model.aps {total:.1f} s"
    )


run(fresh, "round-2 pairs without a round-1 report")
model.corrections.rendered = None
model.corrections.fallback = None
run(round1.sample(len(fresh), random_state=0), "round-1 pairs")
