"""How close to the noise floor the antenna-adjustment target sits on the shipped scenario.

On the cells an adjustment leaves unchanged, round 2 measures the same channel as round 1 with fresh
noise (SPEC §6: 2 dB log-normal, 1 dB quantisation).  So the round-1 measurement itself ("replay")
is a per-grid predictor that knows every (cell, grid, beam) exactly up to one draw of noise; the
oracle (true APS through A′) has none of it.  The script prints, per beam type, the MAE of replay,
WNOMP (fitted here) and the oracle over the same rows: all cells, unchanged and changed cells
(replay only where the pair and beam were reported in both rounds), and the 0.8 × WNOMP target.

Usage: python experiments/noise_floor.py   (about a minute on 2 cores)
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from rflscm.data import BEAM_TYPES, load_scenario
from rflscm.eval.evaluate import run_evaluation
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY
from rflscm.sim import default_scenario_path
from rflscm.train import fit


def replay(scen, beam_type: str, pairs: pd.DataFrame, width: int) -> np.ndarray:
    """Round-1 RSRP [dBm] of the same (cell, grid, beam) as each round-2 row (NaN where not reported)."""
    pairs1, rsrp1 = scen.rsrp_table(1, beam_type)
    index = pd.MultiIndex.from_frame(pairs1[["cell_id", "grid_id"]])
    rows = index.get_indexer(pd.MultiIndex.from_frame(pairs[["cell_id", "grid_id"]]))
    out = np.full((len(pairs), width), np.nan)
    found = rows >= 0
    k = min(width, rsrp1.shape[1])
    out[found, :k] = rsrp1[rows[found], :k]
    return out


def mae(pred: np.ndarray, measured: np.ndarray, rows: np.ndarray, keep: np.ndarray) -> float:
    err = np.abs(pred - measured)[rows][keep[rows]]
    return float(err.mean())


def main() -> None:
    scen = load_scenario(default_scenario_path())
    model = MODEL_REGISTRY["wnomp"].build(None, AngleGrid(), "cpu")
    fit(model, scen, progress=False)
    ev = run_evaluation(model, scen, max_aps_pairs=10)
    print("MAE [dB] on round 2, SSB / CSI-RS; replay = the round-1 measurement of the same beam")
    print(f"{'rows':<40}{'beams':>8}{'replay':>9}{'WNOMP':>9}{'oracle':>9}{'0.8×WNOMP':>11}")
    for beam_type in BEAM_TYPES:
        res = ev.beams[beam_type]
        again = replay(scen, beam_type, res.pairs, res.measured.shape[1])
        scored = np.isfinite(res.measured) & np.isfinite(res.model)
        both = scored & np.isfinite(again)  # reported in both rounds
        lines = (
            ("all cells", np.ones(len(res.pairs), bool), scored),
            ("changed cells", res.changed, scored),
            ("unchanged cells", ~res.changed, scored),
            ("unchanged, reported in both rounds", ~res.changed, both),
        )
        for label, rows, keep in lines:
            w, o = mae(res.model, res.measured, rows, keep), mae(res.oracle, res.measured, rows, keep)
            r = f"{mae(again, res.measured, rows, keep):.2f}" if keep is both else "—"  # replay: same codebook only
            print(f"{beam_type + ', ' + label:<40}{int(keep[rows].sum()):>8}{r:>9}{w:>9.2f}{o:>9.2f}{0.8 * w:>11.2f}")


if __name__ == "__main__":
    main()
