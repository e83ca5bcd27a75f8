"""The `rflscm` command with a training-loss variant patched in, for 10-minute A/Bs that need no new option (issue 28).

Usage (from the repository root; every argument after the script goes to `rflscm`):

    TV_W=0.2 PYTHONPATH=src python experiments/loss_variants.py --threads 1 train SCENARIO --minutes 10 --out A.ckpt
    HUBER_D=0.3 PYTHONPATH=src python experiments/loss_variants.py --threads 1 train SCENARIO --minutes 10 --out B.ckpt

* ``TV_W``: adds TV_W × a total variation of every VM factor (the mean squared difference of neighbouring entries of
  each plane and line of both stages' δ and feature tensors) to the HiTAM loss; its value is printed every 200 steps.
* ``HUBER_D``: the fidelity in bels becomes a Huber loss, squared within HUBER_D bels of the report and linear beyond
  (the missing-beam penalty and the L1 term as before).

Then `rflscm evaluate` as usual: a checkpoint written this way loads and predicts like any other (the variants change
training only). DECISIONS, "Not kept: a total-variation term on the VM factors" and "Not kept: a Huber fidelity".
"""

from __future__ import annotations

import os
import sys

import torch

from rflscm.models.rflscm import model as model_module

TV_W = float(os.environ.get("TV_W", "0"))
HUBER_D = float(os.environ.get("HUBER_D", "0"))
_training_losses = model_module.RFLSCM.training_losses
_steps = [0]


def _tv(vm) -> torch.Tensor:
    total = torch.zeros(())
    for p in vm.planes:
        total = total + (p[:, :, 1:] - p[:, :, :-1]).square().mean() + (p[..., 1:] - p[..., :-1]).square().mean()
    for line in vm.lines:
        total = total + (line[:, :, 1:] - line[:, :, :-1]).square().mean()
    return total


def training_losses(self, pairs, position):
    out = _training_losses(self, pairs, position)
    tv = sum(_tv(stage.fields.delta_vm) + _tv(stage.fields.feature_vm) for stage in self.stages.values())
    out["total"] = out["total"] + TV_W * tv
    _steps[0] += 1
    if _steps[0] % 200 == 1:
        print(f"[tv] step {_steps[0]} loss {float(out['total'].detach()):.4f} tv {float(tv.detach()):.4f}", file=sys.stderr, flush=True)
    return out


def huber_loss(pred, rsrp, beam_mask, aps, x_scale, bound, fidelity="log", sparsity_weight=1e-3, penalty_weight=0.5,
               floor=1e-12):
    bound = torch.as_tensor(bound, dtype=pred.dtype, device=pred.device).expand_as(pred)
    observed = beam_mask & ~torch.isnan(rsrp)
    missing = beam_mask & torch.isnan(rsrp) & ~torch.isnan(bound)
    bound = torch.where(missing, bound, torch.ones_like(bound))
    n = max(pred.shape[0], 1)
    pred_b = torch.log10(pred + floor)
    err = pred_b - torch.log10(torch.where(observed, rsrp, torch.ones_like(rsrp)))
    a = err.abs()
    hub = torch.where(a < HUBER_D, err.square(), 2 * HUBER_D * a - HUBER_D**2)
    excess = torch.relu(pred_b - torch.log10(bound))
    fid = torch.where(observed, hub, torch.zeros_like(err)).sum() / n
    pen = torch.where(missing, excess.square(), torch.zeros_like(excess)).sum() / n
    sparsity = sparsity_weight * (aps / x_scale[:, None]).sum() / n
    return {"total": fid + sparsity + penalty_weight * pen, "fidelity": fid, "sparsity": sparsity, "penalty": pen}


if TV_W > 0:
    model_module.RFLSCM.training_losses = training_losses
if HUBER_D > 0:
    model_module.lscm_loss = huber_loss

if __name__ == "__main__":
    from rflscm.cli import main

    sys.argv[0] = "rflscm"
    main()
