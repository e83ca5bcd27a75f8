"""Each pair's anchor moved by the other pairs' anchor deviations at the same grid, after a checkpoint's pass (no
clock, nothing retrained; issue 28; DECISIONS, "The anchor is its reports' mean").

Usage (from the repository root, which puts ``pass_model.py`` on the path):

    PYTHONPATH=src python experiments/anchor_grid_pool.py CHECKPOINT SCENARIO

A pair's anchor deviation is its anchor less its cell's mean anchor.  The UE positions and their fading are the
grid's, shared by every cell that hears it, so a part of a pair's level error may be its grid's: for each group
(``grid``: every pair of the grid; ``site``: the grid's pairs of the same site; ``sector``: of the same site and
azimuth, the co-located cells on both carriers) the script prints the correlation of a pair's deviation with the mean
of the others' in its group (``CORR``), then round 2 with each anchor moved by w × that mean (``POOL``, w 0.3 and 0.6).
"""

from __future__ import annotations

import json
import sys

import numpy as np
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
    model = model_before_its_pass(sc, checkpoint)
    model.finish_training()
    corr = model.corrections
    assert corr.anchors is not None
    index = corr.anchors.index
    cells = sc.cells[1].set_index("cell_id")
    df = pd.DataFrame({"cell": index.get_level_values(0), "grid": index.get_level_values(1)})
    df["a"] = corr.anchors.to_numpy()
    df["site"] = cells.loc[df["cell"], "site_id"].to_numpy()
    df["az"] = cells.loc[df["cell"], "azimuth_deg"].round().to_numpy()
    df["dev"] = df["a"] - df.groupby("cell")["a"].transform("mean")

    def score(tag: str, values: np.ndarray) -> None:
        corr.anchors = pd.Series(values, index=index, name="anchor_db")  # the same index: the pair lookup stays
        evaluation = run_evaluation(model, sc, AdjustProtocol(), oracle=None)
        print("POOL", json.dumps({"anchors": tag} | seen_rows(evaluation, r1_index)), flush=True)

    score("own", df["a"].to_numpy())
    for name, keys in (("grid", ["grid"]), ("site", ["grid", "site"]), ("sector", ["grid", "site", "az"])):
        group = df.groupby(keys)["dev"]
        total, count = group.transform("sum"), group.transform("count")
        others = (total - df["dev"]) / (count - 1).clip(lower=1)
        shared = (count > 1).to_numpy()
        r = float(np.corrcoef(df["dev"][shared], others[shared])[0, 1])
        print("CORR", json.dumps({"group": name, "pairs": int(shared.sum()), "r": round(r, 3)}), flush=True)
        for w in (0.3, 0.6):
            score(f"{name}+{w}", np.where(shared, df["a"] + w * others, df["a"]))


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
