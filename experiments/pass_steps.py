"""Where a trained RF-LSCM's pass after training spends a budget, step by step (issue 29).

    PYTHONPATH=src python experiments/pass_steps.py SCENARIO CHECKPOINT SECONDS

Builds the model from the checkpoint's config, prepares its training data on SCENARIO's round 1, loads the
checkpoint's weights and reruns ``finish_training`` with SECONDS left and ``render_rest`` (as the demo's fit does),
timing the pass's steps (the first pairs' renders, the λ and mix choices, the WNOMP solves, the levels). Prints the
pass's wall time against SECONDS, each step's seconds and what the pass did (DECISIONS, "The pass's own time and the
mix's solves"). The correction loop is a generator, so its own time is what the listed steps leave.
"""

import json
import sys
import time

from pass_model import model_before_its_pass  # experiments/pass_model.py

from rflscm.data import load_scenario
from rflscm.models.rflscm import corrections as C

scenario = load_scenario(sys.argv[1])
checkpoint, seconds = sys.argv[2], float(sys.argv[3])
model = model_before_its_pass(scenario, checkpoint)
spent: dict[str, float] = {}


def timed(owner: object, name: str) -> None:
    inner = getattr(owner, name)

    def step(*args, **kwargs):  # type: ignore[no-untyped-def]
        begun = time.perf_counter()
        out = inner(*args, **kwargs)
        spent[name] = spent.get(name, 0.0) + time.perf_counter() - begun
        return out

    setattr(owner, name, step)


for name in ("_first_pairs", "_choose", "_mix_plan", "_left_over"):
    timed(C, name)
for name in ("fallback", "levels", "render_only"):
    timed(C._Fit, name)
begun = time.perf_counter()
end = begun + seconds
model.finish_training(time_left=lambda: end - time.perf_counter(), render_rest=True)
print(f"pass {time.perf_counter() - begun:.1f} s of {seconds:g}", {k: round(v, 1) for k, v in spent.items()})
print(json.dumps(model.run_info.get("corrections")))
