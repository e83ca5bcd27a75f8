"""Four probes of a checkpoint's angular shape on round 2 (issue 28, deliverable 2).

Usage (from the repository root):

    PYTHONPATH=src python experiments/shape_probes.py cells CHECKPOINT SCENARIO
    PYTHONPATH=src python experiments/shape_probes.py roll CHECKPOINT SCENARIO K1,K2,...
    PYTHONPATH=src python experiments/shape_probes.py partner CHECKPOINT SCENARIO SOURCE:W,...
    PYTHONPATH=src python experiments/shape_probes.py blur CHECKPOINT SCENARIO WE:WA,...

* ``cells``: per cell, round 2's SSB error over the pairs with a round-1 report (raw r = A′x in dBm, no per-beam-type
  offset), the model's and the truth's (the oracle of round 2's UE samples, the model floor's APS), each also with
  every pair's median error removed (its shape), and the signed difference of the model's APS centroid from the
  truth's: elevation weighted by the cell's best round-2 SSB beam gain per bin (``el2``) and by its best round-1 gain
  (``el1``), and the circular azimuth centroid (``az``), in degrees, mean over pairs.  One ``CELL {json}`` line each.
* ``roll``: every pair's APS rolled by K elevation bins (positive: up), then put back at the model's own round-1
  level (:class:`shape_level_split.Hybrid`'s per-pair shift), scored as ``shape_level_split`` scores its hybrids.
* ``partner``: each pair's APS mixed, linearly with weight W, with the APS of its co-located cell on the other
  carrier (same site and azimuth) at the same grid, re-levelled to the pair's own round-1 level; SOURCE ``model`` or
  ``truth`` (the oracle's APS on both sides).
* ``blur``: every pair's APS blurred by a [W, 1 − 2W, W] kernel over neighbouring elevation bins (WE), then over
  neighbouring azimuth bins (WA), put back at the model's own round-1 level as ``roll`` does.

Nothing is written.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import pandas as pd
import torch

sys.path.insert(0, "experiments")
import shape_level_split as S  # noqa: E402

from rflscm.data import load_scenario  # noqa: E402
from rflscm.eval import AdjustProtocol, run_evaluation  # noqa: E402
from rflscm.eval.metrics import changed_cells  # noqa: E402
from rflscm.eval.oracle import OracleModel  # noqa: E402
from rflscm.models import load_model  # noqa: E402
from rflscm.models.source import checked_aps  # noqa: E402


def load(checkpoint: str, scenario: str):
    torch.set_num_threads(1)
    sc = load_scenario(scenario)
    model = load_model(checkpoint, sc, device="cpu")
    oracle = OracleModel.for_scenario(sc, model.angle_grid, "cpu", sample_round=2)
    return sc, model, oracle


def cells(checkpoint: str, scenario: str) -> None:
    sc, model, oracle = load(checkpoint, scenario)
    grid = model.angle_grid
    el = np.degrees(grid.elevations_rad).repeat(grid.num_az)
    az = np.radians(np.tile(np.degrees(grid.azimuths_rad), grid.num_el))
    r1 = [pd.MultiIndex.from_frame(sc.rsrp_table(1, bt)[0]) for bt in ("ssb", "csi")]
    seen = r1[0].union(r1[1])
    pairs2, rsrp2 = sc.rsrp_table(2, "ssb")
    changed = set(int(c) for c in changed_cells(sc, 1, 2))
    for cell in sc.cell_ids():
        rows = np.flatnonzero(pairs2["cell_id"].to_numpy() == cell)
        rows = rows[pd.MultiIndex.from_frame(pairs2.iloc[rows]).isin(seen)]
        if not rows.size:
            continue
        grids = pairs2["grid_id"].to_numpy()[rows]
        ids = np.full(len(rows), cell)
        x = checked_aps(model, ids, grids, None, sc).double()
        t = oracle.aps(ids, grids).double()
        a2 = sc.sensing(cell, "ssb", grid, round=2, dtype=torch.float64)
        a1 = sc.sensing(cell, "ssb", grid, round=1, dtype=torch.float64)
        measured = rsrp2[rows, : a2.shape[0]]
        ok = np.isfinite(measured)

        def errors(aps: torch.Tensor) -> tuple[float, float]:
            d = np.where(ok, 10 * np.log10((aps @ a2.T).clamp_min(1e-30).numpy()) - measured, np.nan)
            return float(np.nanmean(np.abs(d))), float(np.nanmean(np.abs(d - np.nanmedian(d, 1, keepdims=True))))

        def centroid(aps: torch.Tensor, gain: torch.Tensor, values: np.ndarray) -> np.ndarray:
            w = aps.numpy() * gain.max(0).values.numpy()
            return (w * values).sum(1) / np.maximum(w.sum(1), 1e-30)

        def azimuth(aps: torch.Tensor) -> np.ndarray:
            w = aps.numpy() * a2.max(0).values.numpy()
            return np.degrees(np.angle((w * np.exp(1j * az)).sum(1)))

        (model_mae, model_shape), (truth_mae, truth_shape) = errors(x), errors(t)
        row = {
            "cell": int(cell),
            "changed": int(cell) in changed,
            "pairs": int(rows.size),
            "beams": int(ok.sum()),
            "mae_model": round(model_mae, 3),
            "mae_truth": round(truth_mae, 3),
            "shape_model": round(model_shape, 3),
            "shape_truth": round(truth_shape, 3),
            "el2": round(float(np.mean(centroid(x, a2, el) - centroid(t, a2, el))), 2),
            "el1": round(float(np.mean(centroid(x, a1, el) - centroid(t, a1, el))), 2),
            "el_truth": round(float(np.mean(centroid(t, a1, el))), 2),
            "az": round(float(np.mean((azimuth(x) - azimuth(t) + 180.0) % 360.0 - 180.0)), 2),
        }
        print("CELL", json.dumps(row), flush=True)


class Rolled(S.Hybrid):
    """The model's APS rolled by :attr:`k` elevation bins, at the model's own round-1 level."""

    k = 0

    def _elevation_fix(self, cells, truth, x):
        g = self.grid
        return torch.roll(x.view(-1, g.num_el, g.num_az), self.k, 1).reshape(x.shape)


def roll(checkpoint: str, scenario: str, ks: str) -> None:
    sc, model, oracle = load(checkpoint, scenario)
    for k in (int(v) for v in ks.split(",")):
        hybrid = Rolled(model, oracle, sc, "model_shape+truth_elevation")
        hybrid.k = k
        evaluation = run_evaluation(hybrid, sc, AdjustProtocol(), oracle=None)
        print("ROLL", k, json.dumps(S.seen_rows(evaluation, hybrid.r1_index)), flush=True)


class Partnered(S.Hybrid):
    """Each pair's APS mixed with its co-located other-carrier cell's (:attr:`partner`), weight :attr:`w`."""

    w, source, partner = 0.0, "model", {}

    def aps(self, cell_ids, grid_ids, grid_xyz=None):
        def get(ids):
            if self.source == "truth":
                return self.oracle.aps(ids, grid_ids).double()
            return checked_aps(self.model, ids, grid_ids, None, self.sc).double()

        x = get(cell_ids)
        y = get(np.array([self.partner[int(c)] for c in cell_ids]))
        y = y * torch.as_tensor(10.0 ** (self._shift(cell_ids, grid_ids, y, x) / 10.0))[:, None]
        return ((1.0 - self.w) * x + self.w * y).float()


def partner(checkpoint: str, scenario: str, specs: str) -> None:
    sc, model, oracle = load(checkpoint, scenario)
    table = sc.cells[1].set_index("cell_id") if isinstance(sc.cells, dict) else sc.cells.set_index("cell_id")
    mates = {}
    for cell, row in table.iterrows():
        same = table[
            (table.site_id == row.site_id) & (table.azimuth_deg == row.azimuth_deg) & (table.freq_hz != row.freq_hz)
        ]
        mates[int(cell)] = int(same.index[0]) if len(same) else int(cell)
    for spec in specs.split(","):
        source, weight = spec.split(":")
        hybrid = Partnered(model, oracle, sc, "model")
        hybrid.source, hybrid.w, hybrid.partner = source, float(weight), mates
        evaluation = run_evaluation(hybrid, sc, AdjustProtocol(), oracle=None)
        print("PARTNER", spec, json.dumps(S.seen_rows(evaluation, hybrid.r1_index)), flush=True)


class Blurred(S.Hybrid):
    """The model's APS blurred in elevation (:attr:`we`) and azimuth (:attr:`wa`), at its own round-1 level."""

    we, wa = 0.0, 0.0

    def _elevation_fix(self, cells, truth, x):
        v = x.view(-1, self.grid.num_el, self.grid.num_az)
        if self.we:  # the top and bottom rows see themselves beyond the edge
            up, down = torch.cat([v[:, :1], v[:, :-1]], 1), torch.cat([v[:, 1:], v[:, -1:]], 1)
            v = (1 - 2 * self.we) * v + self.we * (up + down)
        if self.wa:  # azimuth wraps around
            v = (1 - 2 * self.wa) * v + self.wa * (torch.roll(v, 1, 2) + torch.roll(v, -1, 2))
        return v.reshape(x.shape)


def blur(checkpoint: str, scenario: str, specs: str) -> None:
    sc, model, oracle = load(checkpoint, scenario)
    for spec in specs.split(","):
        hybrid = Blurred(model, oracle, sc, "model_shape+truth_elevation")
        hybrid.we, hybrid.wa = (float(v) for v in spec.split(":"))
        evaluation = run_evaluation(hybrid, sc, AdjustProtocol(), oracle=None)
        print("BLUR", spec, json.dumps(S.seen_rows(evaluation, hybrid.r1_index)), flush=True)


if __name__ == "__main__":
    {"cells": cells, "roll": roll, "partner": partner, "blur": blur}[sys.argv[1]](*sys.argv[2:])
