"""Does an average of the field's weights over the end of training predict round 2 better than the last step's
weights (issue 28, deliverable 2)?

    PYTHONPATH=src python experiments/weight_average.py SCENARIO STEPS SEED [k=v ...]

Trains RF-LSCM (quick preset, ``--set`` style overrides ``k=v``) for STEPS steps in step mode with training seed
SEED, keeping beside the weights several averages of them: exponential moving averages with decays 0.99, 0.995 and
0.998, and a uniform (Polyak) average, each started once training has passed the HiTAM hand-off and its ramp (or
half the schedule, the later). Then, for the last step's weights and each average in turn, the whole pass after
training (no clock) and round 2 over the pairs with round-1 reports: SSB all / changed, CSI-RS all / changed.
"""

import sys

import torch

from rflscm.cli.common import seed_everything
from rflscm.cli.overrides import model_config
from rflscm.data import load_scenario
from rflscm.eval import run_evaluation
from rflscm.eval.protocols import fit_with_protocol
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY
from rflscm.train import trainer as trainer_module

torch.set_num_threads(1)  # two runs side by side on the 2 cores
scenario_path, steps, seed = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
sets = [f"train.steps={steps}", f"train.seed={seed}", *sys.argv[4:]]
scenario = load_scenario(scenario_path)
seed_everything(seed)
model = MODEL_REGISTRY["rflscm"].build(model_config("rflscm", "quick", None, sets), AngleGrid(), "cpu")
hitam = model.config.hitam
start = max(steps // 2, hitam.warmup_steps + hitam.ramp_steps)
DECAYS = (0.99, 0.995, 0.998)
averages: dict[str, list[torch.Tensor]] = {}
count = 0


def params() -> list[torch.Tensor]:
    return [p.detach() for p in model.stages.parameters()]


step = trainer_module.Trainer.train_step


def averaging_step(self):  # type: ignore[no-untyped-def]
    global count
    out = step(self)
    if self.step < start:
        return out
    now = params()
    if not averages:
        averages.update({f"ema {d}": [p.clone() for p in now] for d in DECAYS})
        averages["uniform"] = [p.clone() for p in now]
        count = 1
        return out
    count += 1
    with torch.no_grad():
        for d in DECAYS:
            torch._foreach_lerp_(averages[f"ema {d}"], now, 1 - d)
        torch._foreach_lerp_(averages["uniform"], now, 1 / count)
    return out


trainer_module.Trainer.train_step = averaging_step
finish = model.finish_training
model.finish_training = lambda **kw: None  # the pass runs below, once per set of weights
fit_with_protocol(model, scenario, progress=False)
model.finish_training = finish
last = [p.clone() for p in params()]
print(f"steps {steps}, seed {seed}, averages over steps {start}..{steps} ({count} steps)", flush=True)
for name, weights in [("last step", last), *averages.items()]:
    with torch.no_grad():
        for p, w in zip(model.stages.parameters(), weights, strict=True):
            p.copy_(w)
    model.finish_training()
    seen = run_evaluation(model, scenario, None, oracle=None).metrics["seen"]["mae_db"]
    rows = " / ".join(f"{seen[bt][subset]:.3f}" for bt in ("ssb", "csi") for subset in ("all", "changed"))
    print(f"{name:>10}: round 2 {rows}", flush=True)
