"""How much of a checkpoint's round-2 error on the changed cells is a bias per (cell, beam) or a level per pair
(issue 28; DECISIONS, "The shape fidelity in the demos, B1 and B6").

Usage (from the repository root; ``ORACLE=1`` scores the model floor's oracle, the truth of round 2's UE samples,
instead of the checkpoint):

    [ORACLE=1] PYTHONPATH=src python experiments/beam_bias.py CHECKPOINT SCENARIO

For each beam type, over the changed cells' pairs with a round-1 report: the MAE [dB], the MAE once each (cell, beam)'s
mean error is removed (what a per-beam correction learnt from round 2 itself would reach), once each pair's median
error is removed, and the mean signed error.  Then (``BEAM`` lines) each beam's mean signed error over the changed
cells that use one round-2 codebook, with the number of errors behind it, so a beam that lights directions round 1's
beams barely saw shows as a bias of its own.
"""

from __future__ import annotations

import json
import os
import sys

import numpy as np
import pandas as pd
import torch

from rflscm.data import load_scenario
from rflscm.eval import AdjustProtocol, run_evaluation
from rflscm.eval.oracle import OracleModel
from rflscm.models import load_model


def main(checkpoint: str, scenario: str) -> None:
    torch.set_num_threads(1)
    sc = load_scenario(scenario)
    model = load_model(checkpoint, sc, device="cpu")
    source = (
        OracleModel.for_scenario(sc, model.angle_grid, "cpu", sample_round=2) if os.environ.get("ORACLE") else model
    )
    evaluation = run_evaluation(source, sc, AdjustProtocol(), oracle=None)
    r1_index = {bt: pd.MultiIndex.from_frame(sc.rsrp_table(1, bt)[0]) for bt in ("ssb", "csi")}
    for bt in ("ssb", "csi"):
        res = evaluation.beams[bt]
        index = pd.MultiIndex.from_frame(res.pairs[["cell_id", "grid_id"]])
        rows = (index.isin(r1_index["ssb"]) | index.isin(r1_index["csi"])) & res.changed
        err = (res.model - res.measured)[rows]
        ok = np.isfinite(err)
        err = np.where(ok, err, np.nan)
        cells = res.pairs["cell_id"].to_numpy()[rows]
        per_beam = err.copy()
        for cell in np.unique(cells):
            mine = cells == cell
            seen = ok[mine].any(0)
            mean = np.zeros(err.shape[1])
            mean[seen] = np.nanmean(err[mine][:, seen], axis=0)
            per_beam[mine] = err[mine] - mean[None, :]
        per_pair = err - np.nanmedian(err, axis=1, keepdims=True)
        row = {
            "beam_type": bt,
            "changed_mae": round(float(np.nanmean(np.abs(err))), 3),
            "less_cell_beam_mean": round(float(np.nanmean(np.abs(per_beam))), 3),
            "less_pair_median": round(float(np.nanmean(np.abs(per_pair))), 3),
            "mean_signed": round(float(np.nanmean(err)), 3),
        }
        print("BIAS", json.dumps(row), flush=True)
        codebooks = sc.cells[2].set_index("cell_id")[f"{bt}_codebook"]
        for book in sorted(set(codebooks.loc[np.unique(cells)])):
            mine = np.isin(cells, codebooks.index[codebooks == book])
            count = np.isfinite(err[mine]).sum(0)
            mean = np.nansum(err[mine], 0) / np.maximum(count, 1)
            beams = {"beam_type": bt, "codebook": book, "cells": int(np.unique(cells[mine]).size)}
            beams |= {"mean_signed": [round(float(v), 2) for v in mean], "errors": count.tolist()}
            print("BEAM", json.dumps(beams), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
