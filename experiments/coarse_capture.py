"""How much of the true APS HiTAM's coarse selection lets the refinement stage reach (issue 28).

Usage (from the repository root, which puts ``pass_model.py`` on the path):

    PYTHONPATH=src python experiments/coarse_capture.py CHECKPOINT SCENARIO

For every training pair of the checkpoint, the share of the true APS (round-1 UE samples, each bin weighted by the
cell's best round-1 beam gain there: the power its beams can receive) that lies inside the K_C coarse blocks the
selection refines, with the blocks chosen

* by the model's coarse power (HiTAM as the paper has it),
* by the model's coarse power times the cell's best round-1 beam gain in the block (the block-mean sensing column),
* by the truth's own coarse power (what a perfect coarse stage would choose),

at K_C = 8 … 48, and by the pair's number of reported round-1 beams; and the live samples per pair the first two
selections render at the checkpoint's K_C (their cost).  A share near 0 means the refinement stage
renders none of the directions the pair's power comes from.  Nothing is written; ``CAPTURE`` lines.
"""

from __future__ import annotations

import json
import sys

import numpy as np
import torch

from pass_model import model_before_its_pass
from rflscm.data import load_scenario
from rflscm.eval.oracle import OracleModel


def main(checkpoint: str, scenario: str) -> None:
    torch.set_num_threads(1)
    sc = load_scenario(scenario)
    model = model_before_its_pass(sc, checkpoint)
    oracle = OracleModel.for_scenario(sc, model.angle_grid, "cpu", sample_round=1)
    train, renderer, hitam = model._training(), model._renderer(), model.hitam
    assert hitam is not None and train.a_coarse is not None
    data = train.data
    pairs = torch.arange(data.num_pairs)
    cells, xyz = data.cell_index[pairs], data.grid_xyz[pairs]
    with torch.no_grad():
        coarse = renderer.coarse_power(cells, xyz)  # [P, Nc]
    gain_coarse = train.a_coarse.max(1).values[cells]  # [P, Nc] best beam's block-mean column
    ids = np.asarray(model.scene.cell_ids)[cells.numpy()]
    truth = oracle.aps(ids, np.asarray(data.grid_ids)[pairs.numpy()], xyz.double().numpy()).double()
    received = truth * train.a_norm.max(1).values[cells].double()  # [P, Nf]
    visible = renderer.visible("coarse")[cells]
    truth_coarse = (truth[:, hitam.children] * hitam.valid).sum(-1).float()

    def share(score: torch.Tensor, top_k: int) -> torch.Tensor:
        top = torch.topk(torch.where(visible, score, torch.full_like(score, -1.0)), top_k, dim=-1).indices
        fine, ok = hitam.mapping.children(top)
        inside = (received.gather(1, fine.flatten(1)) * ok.flatten(1)).sum(1)
        return inside / received.sum(1).clamp_min(1e-30)

    scores = {"model_power": coarse, "model_power_x_gain": coarse * gain_coarse, "truth_power": truth_coarse}
    for top_k in (8, 16, 24, 32, 48):
        row: dict[str, object] = {"top_k": top_k}
        for name, score in scores.items():
            s = share(score, top_k)
            row[name] = {"mean": round(float(s.mean()), 3), "p10": round(float(s.quantile(0.1)), 3)}
        print("CAPTURE", json.dumps(row), flush=True)
    rays = renderer.ray_samples("fine")
    assert rays.live is not None
    for name, score in list(scores.items())[:2]:  # what each selection costs to render: live samples per pair
        top = torch.topk(torch.where(visible, score, torch.full_like(score, -1.0)), hitam.top_k, dim=-1).indices
        fine, ok = hitam.mapping.children(top)
        fine, ok = fine.flatten(1), ok.flatten(1) & renderer.visible("fine")[cells[:, None], fine.flatten(1)]
        live = (rays.live[cells[:, None] * rays.directions.shape[0] + fine] * ok).sum(1).double()
        print("CAPTURE", json.dumps({"selection": name, "live_samples_per_pair": round(float(live.mean()))}), flush=True)
    reports = data.observed.sum(1)
    s = share(coarse, hitam.top_k)
    for lo, hi in ((1, 3), (3, 6), (6, 10), (10, 1000)):
        k = (reports >= lo) & (reports < hi)
        row = {"reports": [lo, hi], "pairs": int(k.sum()), "model_power": round(float(s[k].mean()), 3)}
        print("CAPTURE", json.dumps(row), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
