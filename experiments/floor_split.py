"""Where a trained checkpoint's distance to the model floor lies on round 2 (issue 28, deliverable 2).

Usage (from the repository root, one thread):

    PYTHONPATH=src python experiments/floor_split.py CHECKPOINT SCENARIO

Evaluates ``CHECKPOINT`` on ``SCENARIO`` under the adjustment protocol (round 1 → round 2) with the oracle (the
true APS through the model's own sensing matrices: the model floor), then prints

* ``SPLIT`` lines: per beam type and cell set (all, changed), the MAE of the model and of the oracle split into each
  pair's *level* (the median of its round-2 errors, beam-weighted) and its *shape* (what is left after the level);
* ``CELL`` lines: per changed cell, the mean error (bias) and MAE of the model and the oracle;
* ``REPEAT`` lines: on the beams reported in both rounds, the model, the oracle, the same beam's round-1 report
  taken as the prediction (``repeat``) and the dB average of the model and that report, for the unchanged and the
  changed cells.  On an unchanged cell the round-1 report of the same beam is the truth plus an independent error,
  so it shows how much of one round's own reports a model leaves unused.

Nothing is written; every figure comes from the printed lines.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pandas as pd
import torch

from rflscm.data import load_scenario
from rflscm.eval import AdjustProtocol, run_evaluation
from rflscm.eval.cache import APSCache
from rflscm.models import load_model


def _split(err: np.ndarray, ok: np.ndarray) -> dict:
    e = np.where(ok, err, np.nan)
    beams = ok.sum(1)
    keep = beams > 0
    level = np.nanmedian(e[keep], axis=1)
    return {
        "mae": round(float(np.abs(err[ok]).mean()), 3),
        "level": round(float((np.abs(level) * beams[keep]).sum() / beams.sum()), 3),
        "shape": round(float(np.abs(e[keep] - level[:, None])[ok[keep]].mean()), 3),
    }


def main(checkpoint: str, scenario: str) -> None:
    torch.set_num_threads(1)
    sc = load_scenario(scenario)
    model = load_model(checkpoint, sc, device="cpu")
    ev = run_evaluation(APSCache(model), sc, AdjustProtocol(), oracle="auto")
    table = pd.read_parquet(sc.root / sc.meta.measurements)
    first = table[table["round"] == 1]
    for bt in ("ssb", "csi"):
        res = ev.beams[bt]
        both = np.isfinite(res.measured) & np.isfinite(res.model) & np.isfinite(res.oracle)
        for which, rows in (("all", np.ones(len(res.pairs), bool)), ("changed", res.changed)):
            ok = both & rows[:, None]
            out = {
                name: _split(pred - res.measured, ok) for name, pred in (("model", res.model), ("oracle", res.oracle))
            }
            out["beams"] = int(ok.sum())
            print("SPLIT", bt, which, json.dumps(out), flush=True)
        cells = res.pairs["cell_id"].to_numpy()
        for cell in np.unique(cells[res.changed]):
            ok = both & (cells == cell)[:, None]
            err_m, err_o = (res.model - res.measured)[ok], (res.oracle - res.measured)[ok]
            row = {
                "beams": int(ok.sum()),
                "model_bias": round(float(err_m.mean()), 2),
                "oracle_bias": round(float(err_o.mean()), 2),
            }
            row |= {
                "model_mae": round(float(np.abs(err_m).mean()), 2),
                "oracle_mae": round(float(np.abs(err_o).mean()), 2),
            }
            print("CELL", bt, int(cell), json.dumps(row), flush=True)
        width = res.measured.shape[1]
        wide = first[first["beam_type"] == bt].pivot_table(
            index=["cell_id", "grid_id"], columns="beam_id", values="rsrp_dbm", aggfunc="first"
        )
        repeat = wide.reindex(columns=range(width)).reindex(pd.MultiIndex.from_frame(res.pairs[["cell_id", "grid_id"]]))
        rep = repeat.to_numpy()
        for which, rows in (("unchanged", ~res.changed), ("changed", res.changed)):
            ok = both & np.isfinite(rep) & rows[:, None]

            def mae(pred: np.ndarray, ok: np.ndarray = ok, measured: np.ndarray = res.measured) -> float:
                return round(float(np.abs(pred - measured)[ok].mean()), 3)

            out = {
                "beams": int(ok.sum()),
                "model": mae(res.model),
                "oracle": mae(res.oracle),
                "repeat": mae(rep),
                "model_repeat_avg": mae((res.model + rep) / 2),
            }
            print("REPEAT", bt, which, json.dumps(out), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
