"""A checkpoint's pass after training rerun (no clock) with HiTAM's K_C changed for prediction only (issue 28).

Usage (from the repository root, which puts ``pass_model.py`` on the path):

    PYTHONPATH=src python experiments/refit_top_k.py CHECKPOINT SCENARIO K [K ...]

For the checkpoint's own K_C and each K, the trained model renders K coarse blocks per pair in its pass (the anchors,
levels and posterior are refitted on those renders) and in its predictions, nothing trained; one ``REFIT {json}`` line
each with round 2's MAE over the pairs with a round-1 report (``evaluate``'s ``seen`` rows).
"""

from __future__ import annotations

import json
import sys
import time

import pandas as pd
import torch
from pass_model import model_before_its_pass
from shape_level_split import seen_rows

from rflscm.data import load_scenario
from rflscm.eval import AdjustProtocol, run_evaluation


def main(checkpoint: str, scenario: str, top_ks: list[int]) -> None:
    torch.set_num_threads(1)
    sc = load_scenario(scenario)
    r1_index = {bt: pd.MultiIndex.from_frame(sc.rsrp_table(1, bt)[0]) for bt in ("ssb", "csi")}
    for top_k in [None, *top_ks]:
        model = model_before_its_pass(sc, checkpoint)
        assert model.hitam is not None
        if top_k is not None:
            model.hitam.top_k = top_k
        t0 = time.perf_counter()
        model.finish_training()
        evaluation = run_evaluation(model, sc, AdjustProtocol(), oracle=None)
        row = {"top_k": model.hitam.top_k, "s": round(time.perf_counter() - t0, 1)} | seen_rows(evaluation, r1_index)
        print("REFIT", json.dumps(row), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], [int(k) for k in sys.argv[3:]])
