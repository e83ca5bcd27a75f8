"""A checkpoint's pass after training rerun (no clock) with the APS outside HiTAM's refined blocks zero (the paper's
form) and filled with the coarse model's power (``hitam.outside: coarse``), nothing retrained (issue 28).

Usage (from the repository root, which puts ``pass_model.py`` on the path):

    PYTHONPATH=src python experiments/coarse_fill.py CHECKPOINT SCENARIO

One ``FILL {json}`` line per form with round 2's MAE over the pairs with a round-1 report (``evaluate``'s ``seen``
rows), the seconds the pass and the evaluation took, and the posterior's held-aside round-1 MAE [dB] of its choice
(``held_db``, pair-weighted over its report-count groups; ``held_level_db``: the field with its levels and anchors,
no posterior): the score a choice between the two forms on the training data alone would read.  The option changes
no training step, so a checkpoint trained with either value answers for both.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time

import pandas as pd
import torch
from pass_model import model_before_its_pass
from shape_level_split import seen_rows

from rflscm.data import load_scenario
from rflscm.eval import AdjustProtocol, run_evaluation


def main(checkpoint: str, scenario: str) -> None:
    torch.set_num_threads(1)
    sc = load_scenario(scenario)
    r1_index = {bt: pd.MultiIndex.from_frame(sc.rsrp_table(1, bt)[0]) for bt in ("ssb", "csi")}
    for outside in ("zero", "coarse"):
        model = model_before_its_pass(sc, checkpoint)
        assert model.renderer is not None
        config = dataclasses.replace(model.config, hitam=dataclasses.replace(model.config.hitam, outside=outside))
        model.config = model.renderer.config = config
        t0 = time.perf_counter()
        model.finish_training()
        evaluation = run_evaluation(model, sc, AdjustProtocol(), oracle=None)
        row = {"outside": outside, "s": round(time.perf_counter() - t0, 1)} | seen_rows(evaluation, r1_index)
        post = model.corrections.posterior
        if post is not None and post.groups:  # the held-aside round-1 MAE of each group's choice, pair-weighted
            scored = [g for g in post.groups if g["mae_db"] == g["mae_db"]]  # a group with no held-aside report: NaN
            pairs = sum(g["pairs"] for g in scored)
            row["held_db"] = round(sum(g["pairs"] * g["mae_db"] for g in scored) / max(pairs, 1.0), 4)
            row["held_level_db"] = round(post.scores.get(float("inf"), float("nan")), 4)
        print("FILL", json.dumps(row), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
