"""Post-hoc probe (issue 15): what a per-pair level anchor would be worth on a trained checkpoint.

    PYTHONPATH=src python scripts/pair_anchor_probe.py CHECKPOINT SCENARIO [--shrink 0,2,5]

For every round-1 pair with reported beams, the anchor is the median (measured − predicted) [dB] over
its reported round-1 beams (SSB and CSI-RS pooled, after the model's own level correction), shrunk
towards 0 by n / (n + k) for n beams.  The round-2 prediction of the same (cell, grid) is moved by
the anchor; pairs round 1 never reported keep the model's prediction.  Prints the round-2 MAE
(all / changed cells) and mean signed error for each k, k = "off" being the field with its per-cell level
correction only.  ``train.pair_anchors`` (k = 0) is what this probe measured before it existed.
"""

from __future__ import annotations

import argparse

import pandas as pd

from rflscm.data import load_scenario
from rflscm.eval import AdjustProtocol, run_evaluation
from rflscm.eval.cache import APSCache
from rflscm.models import load_model


class Anchored(APSCache):
    def __init__(self, inner, offsets: pd.Series) -> None:
        super().__init__(inner)
        self.offsets = offsets

    def predict_rsrp(self, scenario, round, beam_type, pairs, chunk=4096):  # type: ignore[override]
        out = super().predict_rsrp(scenario, round, beam_type, pairs, chunk)
        key = pd.MultiIndex.from_frame(pairs[["cell_id", "grid_id"]])
        shift = self.offsets.reindex(key).fillna(0.0).to_numpy()
        return out + shift[:, None]


def residuals(cache: APSCache, scenario) -> pd.DataFrame:
    m = scenario.measurements
    rows = m[((m["round"] == 1) & m["rsrp_dbm"].notna()).to_numpy()]
    parts = []
    for bt, of_type in rows.groupby("beam_type"):
        pairs = of_type[["cell_id", "grid_id"]].drop_duplicates().reset_index(drop=True)
        pred = cache.predict_rsrp(scenario, 1, bt, pairs)
        at = pd.MultiIndex.from_frame(pairs).get_indexer(pd.MultiIndex.from_frame(of_type[["cell_id", "grid_id"]]))
        r = of_type["rsrp_dbm"].to_numpy() - pred[at, of_type["beam_id"].to_numpy()]
        parts.append(pd.DataFrame({"cell_id": of_type["cell_id"].to_numpy(), "grid_id": of_type["grid_id"].to_numpy(),
                                   "resid": r}))  # fmt: skip
    return pd.concat(parts)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("checkpoint")
    ap.add_argument("scenario")
    ap.add_argument("--shrink", default="0,2,5")
    args = ap.parse_args()
    scenario = load_scenario(args.scenario)
    model = load_model(args.checkpoint, scenario)
    model.corrections.anchors = None  # the model's own anchors (corrections.pair_anchors) off: the probe computes its own
    cache = APSCache(model)
    res = residuals(cache, scenario)
    grouped = res.groupby(["cell_id", "grid_id"])["resid"]
    median, count = grouped.median(), grouped.size()
    for k in ["off", *args.shrink.split(",")]:
        offsets = median * 0.0 if k == "off" else median * count / (count + float(k))
        metrics = run_evaluation(Anchored(model, offsets), scenario, AdjustProtocol(), oracle=None).metrics
        mae, bias = metrics["mae_db"], metrics["bias_db"]
        print(f"k={k:>4}: SSB {mae['ssb']['all']:.2f} / {mae['ssb']['changed']:.2f}  CSI {mae['csi']['all']:.2f} / "
              f"{mae['csi']['changed']:.2f}  bias {bias['ssb']['all']:+.2f} / {bias['csi']['all']:+.2f}", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
