"""The pass's measured cost before the first step and after training, and where a demo's RF-LSCM time goes.

    PYTHONPATH=src python experiments/pass_cost.py SCENARIO MINUTES [AFTER_S]

Trains RF-LSCM (quick preset) on SCENARIO's round 1 within MINUTES, as the demo's RF-LSCM is (``AFTER_S``: the
seconds WNOMP's save, evaluation and report took, which the demo passes on), printing each deal of the budget (the
pass's cost as measured then), the pass's time and its choice for the pairs it leaves, then the evaluation's time and
MAE; then measures the pass's cost again on the trained weights (DECISIONS, "The pass keeps its renders").
"""

import sys
import time

from rflscm.cli.overrides import model_config
from rflscm.data import load_scenario
from rflscm.eval import run_evaluation
from rflscm.eval.evaluate import tested_pairs
from rflscm.eval.protocols import AdjustProtocol, fit_with_protocol
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY
from rflscm.models.rflscm.model import RFLSCM
from rflscm.train import trainer

scenario = load_scenario(sys.argv[1])
budget_s = 60.0 * float(sys.argv[2])
after_s = float(sys.argv[3]) if len(sys.argv) > 3 else 0.0
began = time.perf_counter()


def stamp() -> str:
    return f"[{time.perf_counter() - began:6.1f} s]"


deal = trainer.BudgetDeal.stop_s


def dealt(self, cost):
    stop = deal(self, cost)
    print(stamp(), "deal:", cost, f"-> training stops at {stop:.1f} s", flush=True)
    return stop


trainer.BudgetDeal.stop_s = dealt
finish = RFLSCM.finish_training


def finished(self, progress=False, time_left=None, clock=time.perf_counter, **kw):
    print(stamp(), f"pass: {time_left() if time_left else float('nan'):.1f} s left, {sorted(kw)}", flush=True)
    t0 = time.perf_counter()
    finish(self, progress, time_left, clock, **kw)
    left = self.corrections.fallback
    print(stamp(), f"pass took {time.perf_counter() - t0:.1f} s; choice for the pairs left:", left and left.scores)


RFLSCM.finish_training = finished
model = MODEL_REGISTRY["rflscm"].build(model_config("rflscm", "quick", None, []), AngleGrid(), "cpu")
known, fresh = tested_pairs(scenario, AdjustProtocol())
summary = fit_with_protocol(
    model, scenario, AdjustProtocol(), progress=False, budget_s=budget_s, after_pairs=known, after_fresh=fresh,
    after_s=after_s,
)
print(stamp(), "fit:", {k: round(v, 2) for k, v in summary.items()}, flush=True)
t0 = time.perf_counter()
evaluation = run_evaluation(model, scenario, AdjustProtocol(), oracle="auto")
print(stamp(), f"evaluation {time.perf_counter() - t0:.1f} s", evaluation.metrics["timing_s"], evaluation.metrics["mae_db"])
print(stamp(), "the pass measured on the trained weights:", RFLSCM.finish_seconds(model), flush=True)
