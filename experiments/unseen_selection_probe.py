"""Is a field model's low bias at unseen grids the reporting's selection? (docs/DECISIONS.md, issue 15 B4)

Trains RF-LSCM as B4 does (10 % of the quick subset's grids, one variant: ``prior_on`` or ``prior_off``)
and compares its round-2 predictions at the grids it never saw with the noiseless truth
(``truth/rsrp_noiseless``) on every beam at or above r_th, twice: over the (cell, grid) pairs round 2
reported (the pairs B4 scores), and over every pair the truth has.  A model that is unbiased over all
pairs but low on the reported ones is being scored on the pairs whose truth happened to be high.

    python experiments/unseen_selection_probe.py src/rflscm/assets/scenarios/default prior_on [ALPHA_P]

An optional third argument sets α_P (the missing-beam penalty) instead of the default.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pandas as pd
import torch

from rflscm.bench import BenchContext
from rflscm.bench.b04_point_cloud import EXTRA, TRAIN_FRACTION, VARIANTS
from rflscm.bench.harness import bench_size, load_bench_data, merge, restrict_round1, train_and_evaluate
from rflscm.data.io import read_table
from rflscm.eval import AdjustProtocol


def main(scenario: str, variant: str, alpha: float | None = None) -> None:
    torch.set_num_threads(1)
    ctx = BenchContext(size="quick", seeds=1, out_dir="unseen-probe", device="cpu", scenario=scenario)
    data, train_grids = restrict_round1(load_bench_data(ctx, bench_size("quick")), TRAIN_FRACTION, seed=0)
    torch.manual_seed(0)
    over = merge(EXTRA["quick"], VARIANTS[variant])
    if alpha is not None:
        over = merge(over, {"loss": {"missing_penalty": alpha}})
    result = train_and_evaluate(data, "rflscm", AdjustProtocol(), over, 0, "cpu")
    sc = data.scenario
    truth = read_table(sc.root / sc.meta.truth / "rsrp_noiseless.parquet")
    out: dict[str, object] = {"variant": variant, "alpha_p": alpha, "train_grids": len(train_grids)}
    for beam_type in ("ssb", "csi"):
        t = truth[((truth["round"] == 2) & (truth["beam_type"].astype(str) == beam_type)).to_numpy()]
        t = t[t["cell_id"].isin(sc.cell_ids()) & t["grid_id"].isin(sc.grid_ids()) & ~t["grid_id"].isin(train_grids)]
        pairs = t[["cell_id", "grid_id"]].drop_duplicates().sort_values(["cell_id", "grid_id"], ignore_index=True)
        pred = result.model.predict_rsrp(sc, 2, beam_type, pairs)
        row = pd.MultiIndex.from_frame(pairs).get_indexer(pd.MultiIndex.from_frame(t[["cell_id", "grid_id"]]))
        beam = t["beam_id"].to_numpy()
        ok = beam < pred.shape[1]
        err = pred[row[ok], beam[ok]] - t["rsrp_dbm"].to_numpy()[ok]
        above = t["rsrp_dbm"].to_numpy()[ok] >= sc.meta.rsrp_threshold_dbm
        reported_pairs, _ = sc.rsrp_table(2, beam_type)
        reported = pd.MultiIndex.from_frame(t[["cell_id", "grid_id"]][ok]).isin(
            pd.MultiIndex.from_frame(reported_pairs[["cell_id", "grid_id"]])
        )
        block = {}
        for name, rows in (("reported_pairs", above & reported), ("every_pair", above)):
            e = err[rows]
            block[name] = {"beams": int(rows.sum()), "bias_db": float(e.mean()), "mae_db": float(np.abs(e).mean())}
        out[beam_type] = block
    print(json.dumps(out))


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4) or sys.argv[2] not in VARIANTS:
        raise SystemExit(__doc__)
    main(sys.argv[1], sys.argv[2], float(sys.argv[3]) if len(sys.argv) == 4 else None)
