"""How well, and how fast, Adam fits RF-LSCM's attenuation field to the scan's building map (the initialisation).

    PYTHONPATH=src python scripts/attenuation_init_probe.py SCENARIO

Prepares the quick preset on SCENARIO without the initialisation, then fits the δ field's loss channel to the
building targets (``rflscm.models.rflscm.scene.building_targets``) from the same start with several
(learning rate, steps) pairs, one thread, and prints each one's time and RMS error against the targets
(raw log-loss units) and against the channels the fit must keep.  Used for ``RFLSCM.init_fit``
(DECISIONS.md, "Learning faster").
"""

import math
import sys
import time

import torch

import rflscm.models.rflscm.model as rflscm_module
from rflscm.data import load_scenario
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY
from rflscm.models.rflscm.config import INIT_LOSS_DB
from rflscm.models.rflscm.scene import building_targets

torch.set_num_threads(1)
scenario = load_scenario(sys.argv[1])
model = MODEL_REGISTRY["rflscm"].build("quick", AngleGrid(), "cpu")
rflscm_module.RFLSCM._init_attenuation = lambda self, points, share: None  # start from the raw field
model._prepare(scenario)
points, share = building_targets(model.config, scenario, model.prior, seed=0)
target = share * math.log(model.config.field.building_loss_db / INIT_LOSS_DB)
fields = model.all_stages()[0].fields
field = fields.delta_module()
start = {k: v.clone() for k, v in field.state_dict().items()}
with torch.no_grad():
    keep = fields.delta(fields.encode(points))[:, 1:]
torch.optim.Adam(field.parameters())  # the optimiser's first construction imports torch._dynamo: not timed
for lr, steps in [(0.05, 100), (0.05, 50), (0.1, 50), (0.2, 50), (0.1, 30), (0.2, 30)]:
    field.load_state_dict(start)
    began = time.perf_counter()
    rflscm_module.fit_loss_channel(fields, points, target, keep, steps, lr)
    with torch.no_grad():
        out = fields.delta(fields.encode(points))
    rms = float((out[:, 0] - target).square().mean().sqrt())
    kept = float((out[:, 1:] - keep).square().mean().sqrt())
    print(
        f"lr {lr} × {steps} steps: {time.perf_counter() - began:.2f} s, RMS {rms:.3f} (targets' RMS "
        f"{float(target.square().mean().sqrt()):.2f}), kept channels {kept:.4f}"
    )
