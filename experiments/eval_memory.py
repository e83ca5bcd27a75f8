"""The process's memory at each step of ``run_evaluation`` (issue 29).

    PYTHONPATH=src python experiments/eval_memory.py SCENARIO CHECKPOINT

Prints the resident set (current, from ``/proc/self/statm``, and the peak so far, ``ru_maxrss``) after the imports,
the scenario's load, the model's load, the oracle, the predictions of every test pair, each beam type's truth and
bounds, the APS metrics and the metrics' assembly (DECISIONS, "Evaluation caches a cell's APS only while it predicts
that cell").
"""

import importlib
import resource
import sys
import time

begun = time.perf_counter()


def say(what: str) -> None:
    with open("/proc/self/statm") as f:
        current = int(f.read().split()[1]) * 4096 / 2**30
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"[{time.perf_counter() - begun:7.1f} s] {what}: rss {current:.2f} GB, peak {peak:.2f} GB", flush=True)


from rflscm.data import load_scenario  # noqa: E402
from rflscm.eval.protocols import AdjustProtocol  # noqa: E402
from rflscm.models import load_model  # noqa: E402

E = importlib.import_module("rflscm.eval.evaluate")
say("imports")
scenario = load_scenario(sys.argv[1])
say("scenario loaded")
model = load_model(sys.argv[2], scenario, device="cpu")
say("model loaded")


def traced(name: str) -> None:
    inner = getattr(E, name)

    def step(*args, **kwargs):  # type: ignore[no-untyped-def]
        out = inner(*args, **kwargs)
        say(name)
        return out

    setattr(E, name, step)


for name in ("_oracle", "_predict_tests", "_noiseless", "_bounds", "_aps_metrics", "_assemble"):
    traced(name)
evaluation = E.run_evaluation(model, scenario, AdjustProtocol(), oracle="auto")
say("evaluation done")
print(evaluation.metrics["timing_s"], evaluation.metrics["mae_db"])
