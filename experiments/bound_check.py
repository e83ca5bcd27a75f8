"""How often the noiseless truth itself exceeds the missing-beam bounds of a scenario's reporting rule.

For every round and beam type: the missing beams (a bound under :func:`rflscm.data.reporting.missing_bounds`)
whose truth (``truth/rsrp_noiseless``, through the real antenna) lies above the bound, and above it by more
than 3 dB; and the mean and absolute error of the reported beams against the truth (the report error and
the selection of the reporting rule).

    python experiments/bound_check.py src/rflscm/assets/scenarios/default
"""

from __future__ import annotations

import sys

import numpy as np
import pandas as pd

from rflscm.data import load_scenario
from rflscm.data.io import read_table
from rflscm.data.reporting import missing_bounds


def main(root: str) -> None:
    sc = load_scenario(root)
    if sc.meta.truth is None:
        raise SystemExit(f"{root}: the scenario has no truth/ folder")
    truth = read_table(sc.root / sc.meta.truth / "rsrp_noiseless.parquet")
    for rnd in (1, 2):
        for bt in ("ssb", "csi"):
            pairs, meas = sc.rsrp_table(rnd, bt)
            bound = missing_bounds(sc, rnd, bt, pairs, meas)
            t = truth[((truth["round"] == rnd) & (truth["beam_type"].astype(str) == bt)).to_numpy()]
            index = pd.MultiIndex.from_frame(pairs[["cell_id", "grid_id"]].astype("int64"))
            row = index.get_indexer(pd.MultiIndex.from_frame(t[["cell_id", "grid_id"]].astype("int64")))
            beam = t["beam_id"].to_numpy()
            keep = (row >= 0) & (beam < meas.shape[1])
            true = np.full(meas.shape, np.nan)
            true[row[keep], beam[keep]] = t["rsrp_dbm"].to_numpy()[keep]
            missing = np.isfinite(bound) & np.isfinite(true)
            over = (true - bound)[missing]
            reported = np.isfinite(meas) & np.isfinite(true)
            err = (meas - true)[reported]
            print(
                f"round {rnd} {bt}: {int(missing.sum())} missing beams, truth above the bound {np.mean(over > 0):.1%}, "
                f"by > 3 dB {np.mean(over > 3):.1%} | {int(reported.sum())} reported, mean(measured − truth) "
                f"{err.mean():+.2f} dB, MAE {np.abs(err).mean():.2f} dB"
            )


if __name__ == "__main__":
    if len(sys.argv) != 2:
        raise SystemExit(__doc__)
    main(sys.argv[1])
