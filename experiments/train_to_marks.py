"""Train RF-LSCM (quick preset, 3-minute budget schedule, one thread) and save a checkpoint at marks of training time.

    PYTHONPATH=src python experiments/train_to_marks.py SCENARIO OUT_PREFIX 20,45

writes ``OUT_PREFIX_20.ckpt``, ``OUT_PREFIX_45.ckpt`` (each after ``finish_training``, whose time and the
save's are left out of the clock) and stops after the last mark.  Used with
``scripts/pair_posterior_probe.py`` (issue 15; removed, see experiments/README.md).
"""

import contextlib
import sys
import time

import torch

from rflscm.data import load_scenario
from rflscm.eval.protocols import AdjustProtocol, fit_with_protocol
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY

torch.set_num_threads(1)
scen_dir, out, marks = sys.argv[1], sys.argv[2], [float(m) for m in sys.argv[3].split(",")]
scenario = load_scenario(scen_dir)
model = MODEL_REGISTRY["rflscm"].build("quick", AngleGrid(), "cpu")
t0 = time.perf_counter()
excl = [0.0]
nxt = [0]


class Stop(Exception):
    pass


def cb(m):
    t = time.perf_counter() - t0 - excl[0]
    if nxt[0] < len(marks) and t >= marks[nxt[0]]:
        a = time.perf_counter()
        model.finish_training()
        model.save(f"{out}_{int(marks[nxt[0]])}.ckpt")
        print("saved", marks[nxt[0]], "step", m["step"], "t", t, "finish_s", time.perf_counter() - a, flush=True)
        nxt[0] += 1
        excl[0] += time.perf_counter() - a
        if nxt[0] == len(marks):
            raise Stop


with contextlib.suppress(Stop):
    fit_with_protocol(
        model,
        scenario,
        AdjustProtocol(),
        progress=False,
        callback=cb,
        budget_s=180.0,
        clock=lambda: time.perf_counter() - excl[0],
    )
