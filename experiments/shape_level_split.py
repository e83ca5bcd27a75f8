"""Whether a checkpoint's round-2 distance to the model floor is each pair's level or its angular shape (issue 28).

Usage (from the repository root):

    PYTHONPATH=src python experiments/shape_level_split.py CHECKPOINT SCENARIO [ROUND]

Scores round 2 (the pairs with a round-1 report, as ``evaluate``'s ``seen`` rows) with hybrids of the model's APS and
the true one (the oracle of the UE samples of round ``ROUND``, default 2: the model floor's own APS).  Each hybrid
keeps one APS's *angular shape* and moves it, pair by pair, by one dB shift (the median over the pair's reported
round-1 beams, SSB and CSI-RS pooled, of a target minus the APS's own round-1 prediction):

* ``model``: the checkpoint as ``evaluate`` scores it;
* ``truth``: the true APS as it is (the floor when ROUND is 2);
* ``truth_shape+reports``: the true shape, each pair's level from its round-1 reports (what a model with a perfect
  shape and the anchors' level rule would reach);
* ``truth_shape+model_level``: the true shape at the level of the model's own round-1 predictions;
* ``model_shape+truth_level``: the model's shape at the level of the true APS's round-1 predictions;
* ``model_shape+truth_elevation``: the model's APS rolled in elevation so that its mean elevation (weighted by the
  cell's best round-1 SSB beam gain) meets the truth's, then put back at the model's level.

The hybrids have no per-beam-type level offset, so their CSI-RS rows are not comparable with ``model``'s; the SSB rows
are.  Nothing is written; one ``HYBRID {json}`` line per hybrid.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pandas as pd
import torch

from rflscm.data import load_scenario
from rflscm.eval import AdjustProtocol, run_evaluation
from rflscm.eval.oracle import OracleModel
from rflscm.models import load_model
from rflscm.models.source import checked_aps

BEAM_TYPES = ("ssb", "csi")


class Hybrid:
    """An APS source made of the model's and the truth's APS (see the module's docstring)."""

    def __init__(self, model, oracle, scenario, mode: str):
        self.model, self.oracle, self.sc, self.mode = model, oracle, scenario, mode
        self.grid = model.angle_grid
        self.r1 = {bt: scenario.rsrp_table(1, bt) for bt in BEAM_TYPES}
        self.r1_index = {bt: pd.MultiIndex.from_frame(pairs) for bt, (pairs, _) in self.r1.items()}
        el = torch.as_tensor(np.degrees(self.grid.elevations_rad), dtype=torch.float64)
        self.el = el.repeat_interleave(self.grid.num_az)

    def __getattr__(self, key):
        return getattr(self.model, key)

    def rsrp_mix(self, cell_ids, grid_ids, beam_type):
        return None

    def level_offset_db(self, *args, **kwargs):
        return None

    def _shift(self, cells, grids, base, target):
        """Per pair, the median over its reported round-1 beams of (target − base's prediction) [dB]; 0 without."""
        shift = np.zeros(len(cells))
        for cell in np.unique(cells):
            rows = np.flatnonzero(cells == cell)
            diffs: list[list[float]] = [[] for _ in rows]
            for bt in BEAM_TYPES:
                a = self.sc.sensing(cell, bt, self.grid, round=1, dtype=torch.float64)
                at = self.r1_index[bt].get_indexer(pd.MultiIndex.from_arrays([cells[rows], grids[rows]]))
                own = 10 * torch.log10((base[rows] @ a.T).clamp_min(1e-30)).numpy()
                goal = None if target is None else 10 * torch.log10((target[rows] @ a.T).clamp_min(1e-30)).numpy()
                for i, j in enumerate(at):
                    if j < 0:
                        continue
                    measured = self.r1[bt][1][j, : a.shape[0]]
                    reported = np.isfinite(measured)
                    want = measured if goal is None else goal[i]
                    diffs[i].extend((want - own[i])[reported])
            for i, r in enumerate(rows):
                if diffs[i]:
                    shift[r] = np.median(diffs[i])
        return shift

    def _elevation_fix(self, cells, truth, x):
        out = x.clone()
        for cell in np.unique(cells):
            rows = np.flatnonzero(cells == cell)
            gain = self.sc.sensing(cell, "ssb", self.grid, round=1, dtype=torch.float64).max(0).values
            mean_el = []
            for aps in (truth[rows], x[rows]):
                w = aps * gain
                mean_el.append((w * self.el).sum(1) / w.sum(1).clamp_min(1e-30))
            steps = torch.round((mean_el[0] - mean_el[1]) / self.grid.el_step_deg).long()
            for i, r in enumerate(rows):
                if x[r].sum() > 0 and truth[r].sum() > 0:
                    rolled = torch.roll(x[r].view(self.grid.num_el, self.grid.num_az), int(steps[i]), 0)
                    out[r] = rolled.reshape(-1)
        return out

    def aps(self, cell_ids, grid_ids, grid_xyz=None):
        truth = self.oracle.aps(cell_ids, grid_ids, grid_xyz).double()
        x = checked_aps(self.model, cell_ids, grid_ids, grid_xyz, self.sc).double()
        if self.mode == "truth":
            return truth.float()
        base, target = {
            "truth_shape+reports": (truth, None),
            "truth_shape+model_level": (truth, x),
            "model_shape+truth_level": (x, truth),
            "model_shape+truth_elevation": (None, x),
        }[self.mode]
        if base is None:
            base = self._elevation_fix(cell_ids, truth, x)
        shift = self._shift(cell_ids, grid_ids, base, target)
        return (base * torch.as_tensor(10.0 ** (shift / 10.0))[:, None]).float()


def seen_rows(evaluation, r1_index) -> dict[str, float]:
    out = {}
    for bt in BEAM_TYPES:
        res = evaluation.beams[bt]
        index = pd.MultiIndex.from_frame(res.pairs[["cell_id", "grid_id"]])
        seen = index.isin(r1_index["ssb"]) | index.isin(r1_index["csi"])
        ok = np.isfinite(res.measured) & np.isfinite(res.model) & seen[:, None]
        for which, rows in (("all", np.ones(len(seen), bool)), ("changed", res.changed)):
            keep = ok & rows[:, None]
            out[f"{bt}_{which}"] = round(float(np.abs(res.model - res.measured)[keep].mean()), 3)
    return out


def main(checkpoint: str, scenario: str, sample_round: int = 2) -> None:
    torch.set_num_threads(1)
    sc = load_scenario(scenario)
    model = load_model(checkpoint, sc, device="cpu")
    oracle = OracleModel.for_scenario(sc, model.angle_grid, "cpu", sample_round=sample_round)
    modes = [
        "model",
        "truth",
        "truth_shape+reports",
        "truth_shape+model_level",
        "model_shape+truth_level",
        "model_shape+truth_elevation",
    ]
    for mode in modes:
        hybrid = Hybrid(model, oracle, sc, mode)
        source = model if mode == "model" else hybrid
        evaluation = run_evaluation(source, sc, AdjustProtocol(), oracle=None)
        row = {"hybrid": mode, "truth_round": sample_round} | seen_rows(evaluation, hybrid.r1_index)
        print("HYBRID", json.dumps(row), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2], int(sys.argv[3]) if len(sys.argv) > 3 else 2)
