"""A checkpoint's pass after training rerun (no clock) with each pair's anchor as the median of its own reports
(``own``) and pulled toward its cell's mean by how much its reports say (``pooled``, :mod:`rflscm.models.rflscm.
anchors`, the default), nothing retrained (issue 28).

Usage (from the repository root, which puts ``pass_model.py`` on the path):

    PYTHONPATH=src python experiments/anchor_shrink.py CHECKPOINT SCENARIO

One ``ANCHORS {json}`` line per form with round 2's MAE over the pairs with a round-1 report (``evaluate``'s ``seen``
rows: SSB and CSI-RS, all and changed cells), κ = σ²/τ² of the pull (``own``: not measured) and the seconds the pass
and the evaluation took.  Both forms run on the same trained weights, so the difference is the anchors' alone.
"""

from __future__ import annotations

import json
import math
import sys
import time

import pandas as pd
import torch
from pass_model import model_before_its_pass
from shape_level_split import seen_rows

import rflscm.models.rflscm.corrections as corrections
from rflscm.data import load_scenario
from rflscm.eval import AdjustProtocol, run_evaluation


def _own(anchor: torch.Tensor, *_: torch.Tensor) -> tuple[torch.Tensor, float]:
    return anchor, math.nan


def main(checkpoint: str, scenario: str) -> None:
    torch.set_num_threads(1)
    sc = load_scenario(scenario)
    r1_index = {bt: pd.MultiIndex.from_frame(sc.rsrp_table(1, bt)[0]) for bt in ("ssb", "csi")}
    pooled = corrections.shrunk_anchors
    for form, shrink in (("own", _own), ("pooled", pooled)):
        corrections.shrunk_anchors = shrink
        model = model_before_its_pass(sc, checkpoint)
        t0 = time.perf_counter()
        model.finish_training()
        evaluation = run_evaluation(model, sc, AdjustProtocol(), oracle=None)
        row = {
            "anchors": form,
            "kappa": round(model.corrections.anchor_kappa, 3),
            "s": round(time.perf_counter() - t0, 1),
        }
        print("ANCHORS", json.dumps(row | seen_rows(evaluation, r1_index)), flush=True)
    corrections.shrunk_anchors = pooled


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
