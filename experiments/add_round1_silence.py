"""Attach round 1's silence table to a tiled RF-LSCM checkpoint trained before it existed (issue 28).

Emulates what training stores since ``6b9b3c2`` (``RoundOneCensor``: per tile, the (cell, grid) pairs its cells
reported in round 1, the grids those reports came from, and the scenario's threshold), so that the cap's effect can
be measured on one trained model with ``rflscm evaluate`` before and after (DECISIONS, "Kept: pairs round 1 did not
report").  Only for scenarios whose SSB reporting rule is ``threshold`` or ``top_n``.

Usage (from the repository root):

    PYTHONPATH=src python experiments/add_round1_silence.py SCENARIO TILED.ckpt OUT.ckpt
"""

from __future__ import annotations

import sys

import numpy as np
import pandas as pd

from rflscm.data.loader import load_scenario
from rflscm.models.base import load_model
from rflscm.models.rflscm.corrections import RoundOneCensor


def main(scenario_path: str, checkpoint: str, out: str) -> None:
    scen = load_scenario(scenario_path)
    model = load_model(checkpoint, scen)
    m = scen.measurements
    reported = m[(m["round"] == 1) & m["rsrp_dbm"].notna()][["cell_id", "grid_id"]].drop_duplicates()
    for tile, cells in zip(model.tiles, model.tile_cells, strict=True):
        mine = reported[reported["cell_id"].isin(cells)]
        threshold = float(scen.meta.rsrp_threshold_dbm)
        tile.corrections.censor = RoundOneCensor(pd.MultiIndex.from_frame(mine), np.unique(mine["grid_id"]), threshold)
    model.save(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main(*sys.argv[1:4])
