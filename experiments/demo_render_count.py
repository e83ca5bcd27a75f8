"""`rflscm demo` with every `renderer.output` call of RF-LSCM counted and timed (issue 29).

    PYTHONPATH=src python experiments/demo_render_count.py demo --scenario SCENARIO --out OUT --no-progress

Runs the command line as `rflscm` does (its arguments follow the script's name) after wrapping the renderer's
`output`; prints the calls, pairs and seconds rendered up to each `run_evaluation` (WNOMP's renders nothing) and at
the end. Used for the 222-cell demo's rerun in DECISIONS, "Where the 222-cell demo's last overrun came from".
"""

import os
import sys
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # as `rflscm` sets it, before torch loads

import rflscm.eval  # noqa: E402
from rflscm.cli import main  # noqa: E402
from rflscm.models.rflscm import renderer  # noqa: E402

output = renderer.APSRenderer.output
evaluate = rflscm.eval.run_evaluation
counts = [0, 0, 0.0]  # calls, pairs, seconds


def counted(self, cells, xyz, position):
    t0 = time.perf_counter()
    out = output(self, cells, xyz, position)
    counts[0] += 1
    counts[1] += len(cells)
    counts[2] += time.perf_counter() - t0
    return out


def evaluation(*args, **kwargs):
    before = list(counts)
    t0 = time.perf_counter()
    result = evaluate(*args, **kwargs)
    print(
        f"run_evaluation {time.perf_counter() - t0:.1f} s {result.metrics['timing_s']}; renders before it "
        f"{before[0]} calls, {before[1]} pairs, {before[2]:.1f} s; in it {counts[0] - before[0]} calls, "
        f"{counts[1] - before[1]} pairs, {counts[2] - before[2]:.1f} s",
        flush=True,
    )
    return result


renderer.APSRenderer.output = counted
rflscm.eval.run_evaluation = evaluation
sys.argv = ["rflscm", *sys.argv[1:]]
main()
