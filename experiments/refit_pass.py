"""A trained RF-LSCM checkpoint's pass after training rerun under a time budget, nothing trained (issue 28).

    PYTHONPATH=src python experiments/refit_pass.py SCENARIO CHECKPOINT SECONDS OUT.ckpt MIX_WEIGHTS [measure]

Builds the model from the checkpoint's config, prepares its training data on SCENARIO's round 1, loads the
checkpoint's weights and reruns ``finish_training`` with SECONDS of time left and ``MIX_WEIGHTS`` (comma-separated)
as the dB mix's candidate weights (with ``measure``, after the budget's own measurement of the pass, as a ``train`` or
``demo`` run has it: ``finish_seconds``); prints what the pass did and the mix's choice, and writes OUT.ckpt for
``experiments/common_pairs.py`` (DECISIONS, "Kept: WNOMP alone is a candidate of the dB mix").  The budget's clock
decides how many pairs the pass reaches, so two runs correct slightly different pairs.
"""

import json
import sys
import time

import torch
from pass_model import model_before_its_pass  # experiments/pass_model.py

from rflscm.data import load_scenario
from rflscm.models.rflscm import corrections

scenario_path, checkpoint, seconds, out = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4]
scenario = load_scenario(scenario_path)
model = model_before_its_pass(scenario, checkpoint)
corrections.MIX_WEIGHTS = tuple(map(float, sys.argv[5].split(",")))
if len(sys.argv) > 6 and sys.argv[6] == "measure":
    model.finish_seconds()
begun = time.perf_counter()
end = begun + seconds
model.finish_training(time_left=lambda: end - time.perf_counter())
print(f"pass {time.perf_counter() - begun:.1f} s", json.dumps(model.run_info.get("corrections")))
for name in ("mix", "mix_csi"):
    mix = getattr(model.corrections, name, None)
    if mix is not None and mix.weight is not None:
        print(name, "weights", torch.unique(mix.weight).tolist(), "scores", mix.scores)
model.save(out)
