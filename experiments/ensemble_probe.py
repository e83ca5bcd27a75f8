"""Would an ensemble of RF-LSCM models beat one model trained for their total time (issue 28, deliverable 2)?

    PYTHONPATH=src python experiments/ensemble_probe.py SCENARIO CKPT [CKPT ...]

Evaluates each checkpoint on round 2 (the scored pairs with round-1 reports, SSB all / changed, CSI-RS all /
changed), then the mean of their predicted RSRP in dB and in mW over the same pairs. Train the members with
``rflscm --threads 1 train SCENARIO --set train.steps=N --set train.seed=S`` (half the steps each for two members of
one model's time).
"""

import sys

import numpy as np

from rflscm.data import load_scenario
from rflscm.eval import metrics as M
from rflscm.eval import run_evaluation
from rflscm.models import load_model

scenario = load_scenario(sys.argv[1])
runs = [run_evaluation(load_model(path, scenario), scenario, None, oracle=None) for path in sys.argv[2:]]


def rows_text(predict) -> str:  # type: ignore[no-untyped-def]
    out = []
    for bt in ("ssb", "csi"):
        res = runs[0].beams[bt]
        rows = res.rows() & res.seen
        for subset in (rows, rows & res.changed):
            out.append(M.mae_db(M.abs_error_db(predict(bt), res.measured), subset))
    return " / ".join(f"{v:.3f}" for v in out)


for path, run in zip(sys.argv[2:], runs, strict=True):
    seen = run.metrics["seen"]["mae_db"]
    print(path, "evaluate:", " / ".join(f"{seen[bt][k]:.3f}" for bt in ("ssb", "csi") for k in ("all", "changed")))
    print(path, "recomputed:", rows_text(lambda bt, run=run: run.beams[bt].model))
print("mean in dB:", rows_text(lambda bt: np.mean([r.beams[bt].model for r in runs], axis=0)))
print(
    "mean in mW:", rows_text(lambda bt: 10 * np.log10(np.mean([10 ** (r.beams[bt].model / 10) for r in runs], axis=0)))
)
