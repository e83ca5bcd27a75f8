"""The demo's work after each fit (save, evaluation, report) on a finished demo folder, and what a budget's fit
would price RF-LSCM's renders of the test pairs without a round-1 report at, against what they take (issue 29).

    PYTHONPATH=src python experiments/after_fit_cost.py SCENARIO DEMO_FOLDER

Loads DEMO_FOLDER's `wnomp.ckpt` and `rflscm.ckpt`, times each model's save (to a temporary folder), evaluation
(`run_evaluation`, the demo's protocol and oracle) and report, as `rflscm demo` runs them after its fit. For RF-LSCM
it first prices the evaluation's fresh pairs (`tested_pairs`) with `RFLSCM._fresh_render_s` twice (the first warms
the renderer up), then counts and times every `renderer.output` call of the evaluation itself. The last line sets
the deal's reserve, `1.2 × (fresh pairs × price + WNOMP's after-fit work)`, beside RF-LSCM's after-fit work
(DECISIONS, "The caller's renders priced by its calls").
"""

import sys
import tempfile
import time
from pathlib import Path

from rflscm.data import load_scenario
from rflscm.eval import AdjustProtocol, run_evaluation
from rflscm.eval.evaluate import tested_pairs
from rflscm.eval.report import write_report
from rflscm.models import load_model

scenario = load_scenario(sys.argv[1])
folder = Path(sys.argv[2])
_known, fresh = tested_pairs(scenario, AdjustProtocol())
after: dict[str, float] = {}
calls = [0, 0, 0.0]  # renderer.output calls, pairs, seconds
price = 0.0
for name in ("wnomp", "rflscm"):
    model = load_model(folder / f"{name}.ckpt")
    if name == "rflscm":
        output = model.renderer.output

        def timed(cells, xyz, position):
            t0 = time.perf_counter()
            out = output(cells, xyz, position)
            calls[0] += 1
            calls[1] += len(cells)
            calls[2] += time.perf_counter() - t0
            return out

        model.renderer.output = timed
        for _ in range(2):
            price = model._fresh_render_s(fresh, float(model.config.train.steps), time.perf_counter)
            print(f"fresh pairs priced at {price * 1e3:.2f} ms a pair: {price * len(fresh):.1f} s for {len(fresh)}")
        calls[:] = [0, 0, 0.0]
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        model.save(Path(tmp) / "m.ckpt")
        t1 = time.perf_counter()
        evaluation = run_evaluation(model, scenario, AdjustProtocol(), oracle="auto")
        t2 = time.perf_counter()
        write_report(evaluation, scenario, model, Path(tmp) / "report")
        t3 = time.perf_counter()
    after[name] = t3 - t0
    print(
        f"{name}: save {t1 - t0:.1f} s, evaluation {t2 - t1:.1f} s {evaluation.metrics['timing_s']}, "
        f"report {t3 - t2:.1f} s, all {after[name]:.1f} s"
    )
print(f"the evaluation's renders: {calls[0]} calls, {calls[1]} pairs, {calls[2]:.1f} s")
kept = 1.2 * (price * len(fresh) + after["wnomp"])
print(f"kept by the deal {kept:.1f} s, RF-LSCM's after-fit work {after['rflscm']:.1f} s")
