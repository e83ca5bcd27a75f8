"""RF-LSCM against WNOMP on the pairs both answer: round-2 MAE split by what answers each pair in RF-LSCM (issue 28).

``rflscm evaluate`` scores each model on the test pairs it can answer: WNOMP skips the pairs without round-1 reports
(its "unsupported" note), a field model answers them too, so their rows cover different pairs.  This scores both
checkpoints on the round-2 reported beams of the pairs with round-1 reports (the ones WNOMP answers), all and
changed cells (tilt, azimuth or codebook changed from round 1), and splits RF-LSCM's pairs by what answers them:
WNOMP's APS of the pair's reports (``fallback``: pairs a budget's pass did not reach), the posterior (``posterior``,
with the dB mix where it applies) or the field with its level and anchor (``anchor``).

Usage (from the repository root):

    PYTHONPATH=src python experiments/common_pairs.py SCENARIO RFLSCM.ckpt WNOMP.ckpt

Prints one line per beam type × cells × category: reports, RF-LSCM MAE, WNOMP MAE, difference [dB].
"""

from __future__ import annotations

import sys

import numpy as np
import pandas as pd

from rflscm.data.loader import load_scenario
from rflscm.models.base import load_model
from rflscm.models.source import predict_rsrp

CHANGED = (
    "mech_tilt_deg != mech_tilt_deg_1 or elec_tilt_deg != elec_tilt_deg_1 or azimuth_deg != azimuth_deg_1 "
    "or ssb_codebook != ssb_codebook_1 or csi_codebook != csi_codebook_1"
)


def main(scenario_path: str, rflscm_path: str, wnomp_path: str) -> None:
    scen = load_scenario(scenario_path)
    rf, wn = load_model(rflscm_path, scen), load_model(wnomp_path, scen)
    both = scen.cells[2].merge(scen.cells[1], on="cell_id", suffixes=("", "_1"))
    changed = set(both.query(CHANGED)["cell_id"].astype(int))
    category: dict[tuple[int, int], str] = {}
    for tile in getattr(rf, "tiles", [rf]):
        c = tile.corrections
        for name, table in (("anchor", c.anchors), ("posterior", c.posterior), ("fallback", c.fallback)):
            if table is not None:
                category.update({(int(a), int(b)): name for a, b in table.index})
    meas = scen.measurements
    reported = meas["rsrp_dbm"].notna()
    seen = pd.MultiIndex.from_frame(meas.loc[(meas["round"] == 1) & reported, ["cell_id", "grid_id"]].drop_duplicates())
    print(f"{len(changed)} changed cells")
    for bt in ("ssb", "csi"):
        r = meas[(meas["round"] == 2) & (meas["beam_type"] == bt) & reported]
        r = r[pd.MultiIndex.from_frame(r[["cell_id", "grid_id"]]).isin(seen)]
        pairs = r[["cell_id", "grid_id"]].drop_duplicates().reset_index(drop=True)
        at = pd.MultiIndex.from_frame(pairs).get_indexer(pd.MultiIndex.from_frame(r[["cell_id", "grid_id"]]))
        beam, true = r["beam_id"].to_numpy(), r["rsrp_dbm"].to_numpy()
        err = {
            name: np.abs(true - predict_rsrp(m, scen, 2, bt, pairs)[at, beam]) for name, m in (("rf", rf), ("wn", wn))
        }
        cat = np.array([category.get((int(c), int(g)), "none") for c, g in zip(r["cell_id"], r["grid_id"])])
        is_changed = r["cell_id"].isin(changed).to_numpy()
        for cells, sel in (("all", np.ones(len(r), bool)), ("changed", is_changed)):
            for name in ("all", "fallback", "posterior", "anchor", "none"):
                ok = sel & (True if name == "all" else cat == name) & np.isfinite(err["rf"]) & np.isfinite(err["wn"])
                if ok.any():
                    a, b = err["rf"][ok].mean(), err["wn"][ok].mean()
                    print(
                        f"{bt} {cells:8s} {name:10s} reports {int(ok.sum()):8d}  RF-LSCM {a:.3f}  WNOMP {b:.3f}  {a - b:+.3f}"
                    )


if __name__ == "__main__":
    main(*sys.argv[1:4])
