"""Post-hoc probe (issue 15): what a per-pair APS posterior would be worth on a trained checkpoint.

    PYTHONPATH=src python scripts/pair_posterior_probe.py CHECKPOINT SCENARIO [LAMBDAS [ITERATIONS [BINS]]]

For every round-1 pair, per-bin gains v [dB] on the checkpoint's strongest BINS bins (default 256) fit the
pair's round-1 reports under a ridge λ‖v‖² (Gauss–Newton, ITERATIONS, default 3; also 1 and twice that).
Prints the held-aside MAE of each λ (20 % of the reports held aside) and the round-2 MAE (all / changed) for
each λ and iteration count, λ = inf being the checkpoint as it is.  This probe measured the idea before
``train.pair_posterior`` existed (rflscm.models.rflscm.posterior); it forms the Jacobian explicitly and counts only
the re-weighted bins in a report's power.  ``scripts/train_to_marks.py`` writes the checkpoints it read.
"""

import math
import sys
import time

import numpy as np
import pandas as pd
import torch

from rflscm.data import load_scenario
from rflscm.eval import AdjustProtocol, run_evaluation
from rflscm.eval.cache import APSCache
from rflscm.models import load_model

ckpt, scen_dir = sys.argv[1], sys.argv[2]
lams = [float(v) for v in (sys.argv[3] if len(sys.argv) > 3 else "0.01,0.03,0.1,0.3,1,3").split(",")]
iters = int(sys.argv[4]) if len(sys.argv) > 4 else 3
scenario = load_scenario(scen_dir)
model = load_model(ckpt, scenario)
cache = APSCache(model)
m = scenario.measurements
r1 = m[(m["round"] == 1) & m["rsrp_dbm"].notna()]
pairs = r1[["cell_id", "grid_id"]].drop_duplicates().sort_values(["cell_id", "grid_id"]).reset_index(drop=True)
P = len(pairs)
t0 = time.perf_counter()
X = cache.aps(pairs["cell_id"].to_numpy(), pairs["grid_id"].to_numpy())  # [P, K]
print("aps", X.shape, "nnz/pair", float((X > 0).sum(1).float().mean()), f"{time.perf_counter() - t0:.1f}s", flush=True)
nnz = min(int((X > 0).sum(1).max()), int(sys.argv[5]) if len(sys.argv) > 5 else 256)
bins = torch.topk(X, nnz, dim=1).indices  # [P, nnz]
xs = torch.gather(X, 1, bins)
# stacked sensing [M, K] per cell: ssb then csi, and offsets, measured y [P, M]
cells = np.unique(pairs["cell_id"])
Ms = {}
for c in cells:
    a_s = scenario.sensing(int(c), "ssb", model.angle_grid, round=1, device="cpu")
    a_c = scenario.sensing(int(c), "csi", model.angle_grid, round=1, device="cpu")
    Ms[c] = (a_s, a_c)
Mssb = max(v[0].shape[0] for v in Ms.values())
Mcsi = max(v[1].shape[0] for v in Ms.values())
M = Mssb + Mcsi
A = torch.zeros(P, M, nnz)
Y = torch.full((P, M), float("nan"))
OFF = torch.zeros(P, M)
key = pd.MultiIndex.from_frame(pairs)
for c in cells:
    rows = np.flatnonzero(pairs["cell_id"].to_numpy() == c)
    a_s, a_c = Ms[c]
    bsel = bins[rows]
    A[rows, : a_s.shape[0]] = a_s.float()[:, bsel].permute(1, 0, 2)
    A[rows, Mssb : Mssb + a_c.shape[0]] = a_c.float()[:, bsel].permute(1, 0, 2)
    off = model.level_offset_db(np.array([c]), "csi")
    if off is not None:
        OFF[rows, Mssb:] = float(off[0])
for bt, base in (("ssb", 0), ("csi", Mssb)):
    t = r1[r1["beam_type"] == bt]
    at = key.get_indexer(pd.MultiIndex.from_frame(t[["cell_id", "grid_id"]]))
    Y[at, base + t["beam_id"].to_numpy()] = torch.as_tensor(t["rsrp_dbm"].to_numpy(), dtype=torch.float32)
obs = ~torch.isnan(Y)
g = torch.Generator().manual_seed(0)
hold = obs & (torch.rand(P, M, generator=g) < 0.2)
# keep at least one fitted beam per pair
C = 10.0 / math.log(10.0)


def fit(mask, lam, iters):
    v = torch.zeros(P, nnz)
    for _ in range(iters):
        w = xs * torch.exp(v / C)  # [P, nnz]
        f = torch.einsum("pmn,pn->pm", A, w).clamp_min(1e-30)
        pred = 10 * torch.log10(f) + OFF
        e = torch.where(mask, Y - pred, torch.zeros(()))
        S = A * w[:, None, :] / f[:, :, None]  # shares [P, M, nnz]
        S = S * mask[:, :, None]
        rhs = e + torch.einsum("pmn,pn->pm", S, v)
        G = S @ S.transpose(1, 2) + lam * torch.eye(M)
        z = torch.linalg.solve(G, rhs[..., None])[..., 0]
        v = torch.einsum("pmn,pm->pn", S, z)
    return v


def score(v, mask):
    w = xs * torch.exp(v / C)
    f = torch.einsum("pmn,pn->pm", A, w).clamp_min(1e-30)
    pred = 10 * torch.log10(f) + OFF
    return float((pred - Y).abs()[mask].mean())


print("held-aside MAE, no posterior:", round(score(torch.zeros(P, nnz), hold), 3), flush=True)
best = (score(torch.zeros(P, nnz), hold), float("inf"))
for lam in lams:
    v = fit(obs & ~hold, lam, iters)
    s = score(v, hold)
    print(f"lam {lam}: held-aside {s:.3f}  fit {score(v, obs & ~hold):.3f}", flush=True)
    best = min(best, (s, lam))
print("chosen", best, flush=True)


class Post(APSCache):
    def __init__(self, inner, v):
        super().__init__(inner)
        self.v = v

    def aps(self, cell_ids, grid_ids, grid_xyz=None):
        out = super().aps(cell_ids, grid_ids, grid_xyz)
        at = key.get_indexer(pd.MultiIndex.from_arrays([np.asarray(cell_ids), np.asarray(grid_ids)]))
        ok = np.flatnonzero(at >= 0)
        if ok.size:
            rows = torch.as_tensor(at[ok])
            gain = torch.exp(self.v[rows] / C)
            sub = out[torch.as_tensor(ok)]
            sub.scatter_(1, bins[rows], torch.gather(sub, 1, bins[rows]) * gain)
            out[torch.as_tensor(ok)] = sub
        return out


for lam, it in [(float("inf"), 0)] + [(lm, i) for lm in lams for i in (1, iters, 2 * iters)]:
    v = torch.zeros(P, nnz) if math.isinf(lam) else fit(obs, lam, it)
    met = run_evaluation(Post(model, v), scenario, AdjustProtocol(), oracle=None, max_aps_pairs=0).metrics
    mae = met["mae_db"]
    print(
        f"lam {lam} it {it}: round2 SSB {mae['ssb']['all']:.2f} / {mae['ssb']['changed']:.2f}  CSI {mae['csi']['all']:.2f} / {mae['csi']['changed']:.2f}",
        flush=True,
    )
