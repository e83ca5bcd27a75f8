"""Where RF-LSCM's round-2 error at the test pairs without a round-1 report comes from (issue 28).

    PYTHONPATH=src python experiments/fresh_pair_split.py SCENARIO CHECKPOINT

For the round-2 pairs that round 1 did not report, per beam type: the checkpoint's MAE and mean signed error
[dB] as it predicts them, then with round 1's silence cap switched off, with each pair's own cell's CSI-RS level
correction, with none, with the median of the cells' corrections, and with the unseen-grid blend switched off, each on
changed cells and on the others (DECISIONS, "Kept: the median CSI-RS level correction at a pair round 1 did not
report").
"""

import sys

import numpy as np
import pandas as pd

from rflscm.data import load_scenario
from rflscm.data.measurements import reported_pairs
from rflscm.eval.metrics import changed_cells
from rflscm.eval.protocols import AdjustProtocol
from rflscm.models import load_model
from rflscm.models.source import predict_rsrp

scenario = load_scenario(sys.argv[1])
model = load_model(sys.argv[2], scenario, device="cpu")
protocol = AdjustProtocol()
test, train = protocol.test_set(scenario), protocol.training_scenario(scenario)
seen = pd.MultiIndex.from_frame(reported_pairs(train.measurements))
changed = changed_cells(scenario, 1, 2)

for beam_type in ("ssb", "csi"):
    pairs, measured = test.tables[beam_type]
    fresh = ~pd.MultiIndex.from_frame(pairs).isin(seen)
    sub, truth = pairs[fresh].reset_index(drop=True), measured[fresh]
    moved = sub["cell_id"].isin(changed).to_numpy()[:, None]

    def score(name: str, pred: np.ndarray) -> None:
        err = pred - truth
        ok = np.isfinite(err)
        parts = [f"{np.abs(err[ok & w]).mean():6.2f}" if (ok & w).any() else "   nan" for w in (moved, ~moved)]
        print(f"{beam_type} {name:18s} MAE {np.abs(err[ok]).mean():6.2f} bias {err[ok].mean():6.2f}", end=" ")
        print(f"changed cells {parts[0]} others {parts[1]} ({len(sub)} pairs)")

    score("model", predict_rsrp(model, scenario, 2, beam_type, sub))
    every = model.corrections.level_offset_db(np.arange(len(model.scene.cell_ids)), beam_type)
    median = None if every is None else float(np.median(every))

    def own_cell(cell_ids, beam_type, grid_ids=None):  # type: ignore[no-untyped-def]
        return model.corrections.level_offset_db(model.scene.cell_index(np.asarray(cell_ids)), beam_type)

    for name, attr, off in (
        ("no cap", "round1_caps", lambda c, g: None),
        ("own cell's offset", "level_offset_db", own_cell),
        ("no level offset", "level_offset_db", lambda *a, **k: None),
        ("median offset", "level_offset_db", lambda c, *a, **k: None if median is None else np.full(len(c), median)),
    ):
        kept = getattr(model, attr)
        setattr(model, attr, off)
        score(name, predict_rsrp(model, scenario, 2, beam_type, sub))
        setattr(model, attr, kept)
    weight = model.corrections.unseen_weight
    model.corrections.unseen_weight = 0.0
    score("no unseen blend", predict_rsrp(model, scenario, 2, beam_type, sub))
    model.corrections.unseen_weight = weight
