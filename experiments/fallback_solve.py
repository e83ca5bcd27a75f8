"""WNOMP's fallback solve per pair by how a chunk spans the cells, and the pass's measured cost (issue 29).

    PYTHONPATH=src python experiments/fallback_solve.py SCENARIO

Prepares RF-LSCM (quick preset, untrained) on SCENARIO's round 1 and times the fallback's WNOMP solve (its
`_Fit.solve`) on 1 024 pairs spread over every cell, on 1 024 and 4 096 pairs in the pass's block order, and on 4 096
consecutive pairs (a few cells); then measures the pass three times (`measure_pass`, as the trainer does) and prints
its components and the least pass it implies (DECISIONS, "Kept: WNOMP's fallback solves consecutive pairs").
"""

import sys
import time

import torch

from rflscm.cli.overrides import model_config
from rflscm.data import load_scenario
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY
from rflscm.models.rflscm import corrections as C
from rflscm.models.rflscm import model as M

scenario = load_scenario(sys.argv[1])
model = MODEL_REGISTRY["rflscm"].build(model_config("rflscm", "quick", None, []), AngleGrid(), "cpu")
t0 = time.perf_counter()
model.prepare(scenario)
print(f"prepare {time.perf_counter() - t0:.1f} s")
train = model._training()
data = train.data
visible = torch.as_tensor(model.scene.visible)
fit = C._Fit(model.config.corrections, data, train.num_ssb, len(model.scene.cell_ids), None, train.columns, visible)
pairs = torch.nonzero(data.observed.any(1)).squeeze(1)
solver = C.fallback_solver(model.config.corrections)
later = C._later_pairs(pairs, pairs[:0], 0)
middle = pairs.numel() // 2
for name, sample in [
    ("spread over every cell", C._spread(pairs, 1024)),
    ("pass order, 1 024", later[:1024]),
    ("pass order, 4 096", later[:4096]),
    ("consecutive, 4 096", pairs[middle : middle + 4096]),
]:
    t0 = time.perf_counter()
    fit.solve(sample, data.observed[sample], None, solver)
    dt = time.perf_counter() - t0
    cells = int(data.cell_index[sample].unique().numel())
    print(f"{name}: {sample.numel()} pairs, {cells} cells, {dt:.2f} s, {1e3 * dt / sample.numel():.3f} ms a pair")

measured = M.measure_pass


def printed(*args, **kwargs):
    times = measured(*args, **kwargs)
    print(times)
    return times


M.measure_pass = printed
for _ in range(3):
    t0 = time.perf_counter()
    cost = model.finish_seconds()
    print(f"  measured in {time.perf_counter() - t0:.1f} s: {cost}")
