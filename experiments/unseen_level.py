"""The field's level at grids without reports under the shape fidelity: trained variants, anchors carried to unseen
grids, and the blend with several nearest anchored grids (issue 28, deliverable 3; DECISIONS, "The shape fidelity's
level at grids without reports").

Usage (from the repository root, one thread):

    [LEVEL_RAMP=a,b | SMOOTH_LEVEL=K | PENALTY_ABS=1] PYTHONPATH=src python experiments/unseen_level.py train SCENARIO OUT.pt SEED [CONFIG_JSON]

trains one B6 quick RF-LSCM (20 % of the grids held out, as ``rflscm bench b6 --size quick``) with the variants of
``input_variants.py`` that the environment names patched in, saves it and prints its B6 unseen MAE (``TRAINED``
line, as ``unseen_variants.py train``; ``CONFIG_JSON`` e.g. ``'{"loss": {"fidelity": "shape"}}'``).

    PYTHONPATH=src python experiments/unseen_level.py carry SCENARIO OUT.pt

measures how well the cell's other anchors predict a training pair's anchor (leave one out: the nearest anchored
grid's, and an inverse-square-distance mean of the 4 nearest; ``LOO`` line: correlation, the least-squares share β
and the anchors' mean magnitude before and after) and scores B6's unseen grids with the model's own APS there
multiplied by 10^(β × carried anchor / 10) inside the model's blend (``TEST`` lines, β = 0, 0.5, the LOO's, 1).

    PYTHONPATH=src python experiments/unseen_level.py knear SCENARIO OUT.pt [INNER.pt]

scores the unseen-grid blend (1 − w) × own + w × the mean (plain or inverse-square-distance) of the model's APS at the
cell's k nearest anchored grids, k = 1…6, w = 0.5…0.7 (``FULL`` lines: B6's test grids, MAE pooled over both beam
types and per beam type as B6 reports it); with ``INNER.pt`` (trained with a larger hold-out, ``unseen_variants.py
train SCENARIO INNER.pt 0 0.35``) the same on its extra held-out grids (``INNER`` lines), which may choose k and w
without looking at the test grids.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import torch
from scipy.spatial import cKDTree
from unseen_variants import PROTOCOL, _data, _loaded, _mae_rows

from rflscm.eval import run_evaluation
from rflscm.eval.cache import APSCache
from rflscm.eval.protocols import protocol_from_dict


def train(scenario: str, out: str, seed: int, extra: dict | None) -> None:
    import input_variants  # noqa: F401  (its patches, as the environment names them)
    import unseen_variants

    unseen_variants.train(scenario, out, seed, unseen_variants.HOLDOUT, extra)


def _grid_xyz(data):
    return data.scenario.grids.set_index("grid_id")[["x", "y", "z"]]


def _anchored(model):
    a = model.corrections.anchors
    return a.index.get_level_values("cell_id").to_numpy(), a.index.get_level_values("grid_id").to_numpy(), a


def _neighbours(xyz: np.ndarray, points: np.ndarray, k: int, skip_self: bool) -> tuple[np.ndarray, np.ndarray]:
    k = min(k + skip_self, len(xyz))
    d, i = cKDTree(xyz).query(points, k=k)
    d, i = d.reshape(len(points), k), i.reshape(len(points), k)
    return (d[:, 1:], i[:, 1:]) if skip_self else (d, i)


def _own_aps(model, cell_ids: np.ndarray, grid_ids: np.ndarray, grid_xyz=None) -> torch.Tensor:
    """The model's APS with its unseen-grid blend off (each pair's own APS)."""
    weight = model.corrections.unseen_weight
    model.corrections.unseen_weight = 0.0
    try:
        return model.aps(cell_ids, grid_ids, grid_xyz)
    finally:
        model.corrections.unseen_weight = weight


def _idw(d: np.ndarray) -> np.ndarray:
    w = 1.0 / np.maximum(d, 1.0) ** 2
    return w / w.sum(1, keepdims=True)


class _OwnTimes(APSCache):
    """The model with its own APS at pairs without an anchor scaled by 10^(β × the carried anchor / 10) inside its
    blend (the blend's nearest-grid part unchanged)."""

    def __init__(self, model, xyz_of, kind: str, beta: float) -> None:
        super().__init__(model)
        self.m, self.xyz_of, self.kind, self.beta = model, xyz_of, kind, beta
        self.cells, self.grids, anchors = _anchored(model)
        self.values = anchors.to_numpy(np.float64)
        self.keys = set(zip(self.cells.tolist(), self.grids.tolist(), strict=True))

    def aps(self, cell_ids, grid_ids, grid_xyz=None):
        m, w = self.m, self.m.corrections.unseen_weight
        cell_ids, grid_ids = np.asarray(cell_ids).reshape(-1), np.asarray(grid_ids).reshape(-1)
        own = _own_aps(m, cell_ids, grid_ids, grid_xyz)
        out = m.aps(cell_ids, grid_ids, grid_xyz).clone()
        rows = np.array([i for i, key in enumerate(zip(cell_ids.tolist(), grid_ids.tolist())) if key not in self.keys])
        if not rows.size or self.beta == 0.0:
            return out
        carried = np.zeros(rows.size)
        for cell in np.unique(cell_ids[rows]):
            mine = self.cells == cell
            if not mine.any():
                continue
            r = np.flatnonzero(cell_ids[rows] == cell)
            xyz = self.xyz_of.loc[self.grids[mine]].to_numpy()
            d, i = _neighbours(xyz, self.xyz_of.loc[grid_ids[rows[r]]].to_numpy(), 4, False)
            v = self.values[mine][i]
            carried[r] = v[:, 0] if self.kind == "near" else (_idw(d) * v).sum(1)
        gain = torch.as_tensor(10.0 ** (self.beta * carried / 10.0), dtype=out.dtype, device=out.device)[:, None]
        at = torch.as_tensor(rows, device=out.device)
        out[at] += (1.0 - w) * own[at] * (gain - 1.0)
        return out


def carry(scenario: str, path: str) -> None:
    data, model = _data(scenario), _loaded(path)
    model.finish_training()
    xyz_of = _grid_xyz(data)
    cells, grids, anchors = _anchored(model)
    a = anchors.to_numpy(np.float64)
    near, idw = np.zeros_like(a), np.zeros_like(a)
    for cell in np.unique(cells):
        mine = np.flatnonzero(cells == cell)
        if mine.size < 2:
            continue
        xyz = xyz_of.loc[grids[mine]].to_numpy()
        d, i = _neighbours(xyz, xyz, 4, True)
        near[mine], idw[mine] = a[mine][i[:, 0]], (_idw(d) * a[mine][i]).sum(1)
    loo = {}
    for name, p in (("near", near), ("idw", idw)):
        beta = float((p * a).sum() / max((p * p).sum(), 1e-12))
        loo[name] = {
            "corr": round(float(np.corrcoef(p, a)[0, 1]), 3),
            "beta": round(beta, 3),
            "mean_abs": round(float(np.abs(a).mean()), 3),
            "mean_abs_after": round(float(np.abs(a - beta * p).mean()), 3),
        }
    print("LOO", json.dumps({"anchor_sd_db": round(float(a.std()), 3), **loo}), flush=True)
    for kind in ("near", "idw"):
        for beta in (0.0, 0.5, loo[kind]["beta"], 1.0):
            ev = run_evaluation(_OwnTimes(model, xyz_of, kind, beta), data.scenario, PROTOCOL, oracle=data.oracle)
            u = ev.metrics["unseen"]
            row = {k: {b: round(float(u[k][b]), 3) for b in ("ssb", "csi")} for k in ("mae_db", "bias_db")}
            print("TEST", json.dumps({"kind": kind, "beta": beta, **row}), flush=True)


class _KNearest(APSCache):
    """At pairs without an anchor, (1 − w) × the model's own APS + w × the mean (plain or inverse-square-distance) of
    its APS at the cell's k nearest anchored grids (no reach limit)."""

    def __init__(self, model, xyz_of, k: int, weighting: str, w: float) -> None:
        super().__init__(model)
        self.m, self.xyz_of, self.k, self.weighting, self.w = model, xyz_of, k, weighting, w
        self.cells, self.grids, _ = _anchored(model)
        self.keys = set(zip(self.cells.tolist(), self.grids.tolist(), strict=True))

    def aps(self, cell_ids, grid_ids, grid_xyz=None):
        m = self.m
        cell_ids, grid_ids = np.asarray(cell_ids).reshape(-1), np.asarray(grid_ids).reshape(-1)
        out = _own_aps(m, cell_ids, grid_ids, grid_xyz).clone()
        rows = np.array([i for i, key in enumerate(zip(cell_ids.tolist(), grid_ids.tolist())) if key not in self.keys])
        for cell in np.unique(cell_ids[rows]) if rows.size else []:
            mine = self.cells == cell
            if not mine.any():
                continue
            r = rows[cell_ids[rows] == cell]
            anchored = self.grids[mine]
            d, i = _neighbours(
                self.xyz_of.loc[anchored].to_numpy(), self.xyz_of.loc[grid_ids[r]].to_numpy(), self.k, False
            )
            aps = m.aps(np.repeat(cell, i.size), anchored[i].reshape(-1)).reshape(i.shape[0], i.shape[1], -1)
            wt = _idw(d) if self.weighting == "idw" else np.full(d.shape, 1.0 / d.shape[1])
            mean = (aps * torch.as_tensor(wt, dtype=aps.dtype, device=aps.device)[:, :, None]).sum(1)
            at = torch.as_tensor(r, device=out.device)
            out[at] = (1.0 - self.w) * out[at] + self.w * mean
        return out


def _knear_scores(data, path: str, protocol, grids: dict[str, np.ndarray]) -> dict:
    model = _loaded(path)
    model.finish_training()
    xyz_of, scores = _grid_xyz(data), {}
    for k in (1, 2, 3, 4, 6):
        for weighting in ("mean", "idw") if k > 1 else ("mean",):
            for w in (0.5, 0.6, 0.7):
                ev = run_evaluation(
                    _KNearest(model, xyz_of, k, weighting, w), data.scenario, protocol, oracle=data.oracle
                )
                row = {name: _mae_rows(ev, g)["both"] for name, g in grids.items()}
                u = ev.metrics["unseen"]["mae_db"]
                scores[(k, weighting, w)] = row | {"b6": {b: round(float(u[b]), 3) for b in ("ssb", "csi")}}
    return scores


def knear(scenario: str, full: str, inner: str | None) -> None:
    data = _data(scenario)
    test = PROTOCOL.held_out(data.scenario)
    for (k, weighting, w), row in _knear_scores(data, full, PROTOCOL, {"test": test}).items():
        print("FULL", json.dumps({"k": k, "weighting": weighting, "w": w, **row}), flush=True)
    if inner is None:
        return
    protocol = protocol_from_dict(torch.load(inner, weights_only=False)["model"].run_info["protocol"])
    extra = np.setdiff1d(protocol.held_out(data.scenario), test)
    for (k, weighting, w), row in _knear_scores(data, inner, protocol, {"extra": extra}).items():
        print("INNER", json.dumps({"k": k, "weighting": weighting, "w": w, "extra": row["extra"]}), flush=True)


if __name__ == "__main__":
    torch.set_num_threads(1)
    if sys.argv[1] == "train":
        train(sys.argv[2], sys.argv[3], int(sys.argv[4]), json.loads(sys.argv[5]) if len(sys.argv) > 5 else None)
    elif sys.argv[1] == "carry":
        carry(sys.argv[2], sys.argv[3])
    elif sys.argv[1] == "knear":
        knear(sys.argv[2], sys.argv[3], sys.argv[4] if len(sys.argv) > 4 else None)
    else:
        raise SystemExit(__doc__)
