"""RF-LSCM's posterior pairs against a WNOMP checkpoint, per beam type: what a dB mix with that WNOMP would score (issue 28).

RF-LSCM's posterior pairs are predicted as a dB average of the posterior's and WNOMP's APS of the pair's own reports
(``corrections.mix`` and ``mix_csi``: WNOMP's atom count and each report-count group's weight chosen on held-aside
round-1 reports, per beam type since issue 28's last change; pooled over both before).  This scores, on the round-2 reported beams of those pairs, per beam type and all / changed
cells: RF-LSCM as it is (``cur``), the given WNOMP checkpoint alone (``wn``), and (1 − w) × the posterior alone (the
mix switched off) + w × that WNOMP, in dB, for w = 0, 0.25, 0.5, 0.75, 1.  It reads round 2 to *measure* what a
choice would give; nothing here is a choice a model could make.

Usage (from the repository root):

    PYTHONPATH=src python experiments/mix_by_beam_type.py SCENARIO RFLSCM.ckpt WNOMP.ckpt

Prints one line per beam type × cells: reports, ``cur``, ``wn`` and each w's MAE [dB].
"""

from __future__ import annotations

import sys

import numpy as np
import pandas as pd
import torch

from rflscm.data.loader import load_scenario
from rflscm.models.base import load_model
from rflscm.models.source import predict_rsrp

CHANGED = (
    "mech_tilt_deg != mech_tilt_deg_1 or elec_tilt_deg != elec_tilt_deg_1 or azimuth_deg != azimuth_deg_1 "
    "or ssb_codebook != ssb_codebook_1 or csi_codebook != csi_codebook_1"
)
WEIGHTS = (0.0, 0.25, 0.5, 0.75, 1.0)


def main(scenario_path: str, rflscm_path: str, wnomp_path: str) -> None:
    torch.set_num_threads(1)
    scen = load_scenario(scenario_path)
    rf, alone, wn = load_model(rflscm_path, scen), load_model(rflscm_path, scen), load_model(wnomp_path, scen)
    posterior: set[tuple[int, int]] = set()
    for tile, bare in zip(getattr(rf, "tiles", [rf]), getattr(alone, "tiles", [alone]), strict=True):
        if tile.corrections.posterior is not None:
            posterior.update((int(c), int(g)) for c, g in tile.corrections.posterior.index)
        bare.corrections.mix = bare.corrections.mix_csi = None  # the posterior alone
    both = scen.cells[2].merge(scen.cells[1], on="cell_id", suffixes=("", "_1"))
    changed = set(both.query(CHANGED)["cell_id"].astype(int))
    meas = scen.measurements
    print(f"{len(posterior)} posterior pairs, {len(changed)} changed cells")
    for bt in ("ssb", "csi"):
        r = meas[(meas["round"] == 2) & (meas["beam_type"] == bt) & meas["rsrp_dbm"].notna()]
        keep = np.fromiter(((int(c), int(g)) in posterior for c, g in zip(r["cell_id"], r["grid_id"])), bool, len(r))
        r = r[keep]
        pairs = r[["cell_id", "grid_id"]].drop_duplicates().reset_index(drop=True)
        at = pd.MultiIndex.from_frame(pairs).get_indexer(pd.MultiIndex.from_frame(r[["cell_id", "grid_id"]]))
        beam, true = r["beam_id"].to_numpy(), r["rsrp_dbm"].to_numpy()
        pred = {n: predict_rsrp(m, scen, 2, bt, pairs)[at, beam] for n, m in (("cur", rf), ("post", alone), ("wn", wn))}
        is_changed = r["cell_id"].isin(changed).to_numpy()
        for cells, sel in (("all", np.ones(len(r), bool)), ("changed", is_changed)):
            ok = sel & np.isfinite(pred["cur"]) & np.isfinite(pred["wn"]) & np.isfinite(pred["post"])
            line = f"{bt} {cells:8s} reports {int(ok.sum()):8d}"
            line += f"  cur {np.abs(true - pred['cur'])[ok].mean():.3f}  wn {np.abs(true - pred['wn'])[ok].mean():.3f}"
            for w in WEIGHTS:
                mixed = (1.0 - w) * pred["post"] + w * pred["wn"]
                line += f"  w{w:.2f} {np.abs(true - mixed)[ok].mean():.3f}"
            print(line, flush=True)


if __name__ == "__main__":
    main(*sys.argv[1:4])
