"""The LSCM training loss (paper eqs. (19), (22)–(23); SPEC §3).

L = ‖r − A x̃‖² + β_pen ‖x̃‖₁ + α_P ‖𝟙(r missing) ⊙ [A x̃ − r̄]₊‖²

per (cell, grid) pair, r̄ being each missing beam's upper bound under the scenario's reporting rule
(SPEC §3; :func:`rflscm.data.reporting.missing_bounds`: r_th for a threshold, the weakest reported
beam of a full top-N report, the SS-SINR detection level),, summed over beams and averaged over the pairs of a batch.  Quantities
are in the model's normalised units (r / r_ref, A / a_ref, x / x_ref, so that r = A x holds in
both).  ``fidelity="log"`` compares bels (dB/10) instead of linear power — RSRP spans six
decades, and the linear form lets the strongest pairs dominate; its missing-beam penalty then
compares bels too, and its L1 term is measured relative to each pair's own power scale
(``x_scale``, the least APS power that explains the strongest observed beam), so that weak and
strong pairs are regularised alike.

``fidelity="shape"`` is the log form after each pair's own level: every pair's predictions first move by
b = (1 − s) ē bels, ē its mean log error over its reported beams and s = :data:`LEVEL_KEPT` (not differentiated),
so the gradient keeps the share s of a pair's common error and all of the differences between its beams.  The field
then learns each pair's relative beam levels rather than bending its angular shape to the pairs' level errors
(shadowing, UE positions, a report's bias shared by its beams); the pair anchors after training set each pair's
level from its reports.  It is the profile of a fit with a free level per pair under a prior that weighs as much as
a quarter of the pair's reports (docs/DECISIONS.md, "Each pair's level profiled out of the training loss").
"""

from __future__ import annotations

from typing import Literal

import torch

LEVEL_KEPT = 0.2
"""The share of each pair's mean log error that ``fidelity="shape"`` keeps (a prior on the pair's level worth a
quarter of its reports; a prior of one report lost 0.18–0.19 dB on SSB in the ideal regime, a share of 0.5 lost more on
etoile's: DECISIONS)."""


def lscm_loss(
    pred: torch.Tensor,
    rsrp: torch.Tensor,
    beam_mask: torch.Tensor,
    aps: torch.Tensor,
    x_scale: torch.Tensor,
    bound: torch.Tensor,
    fidelity: Literal["linear", "log", "shape"] = "log",
    sparsity_weight: float = 1e-3,
    penalty_weight: float = 0.5,
    floor: float = 1e-12,
) -> dict[str, torch.Tensor]:
    """Loss terms of a batch.

    Args:
        pred: predicted RSRP A x̃ ``[num_pairs, num_beams]`` (normalised linear power).
        rsrp: measured RSRP ``[num_pairs, num_beams]`` (normalised linear power), NaN = not reported.
        beam_mask: ``[num_pairs, num_beams]`` bool, the beams that take part (exist in the cell's
            codebook, measured for this pair, not held out).
        aps: the rendered APS x̃ ``[num_pairs, num_dirs]`` (normalised).
        x_scale: ``[num_pairs]`` per-pair APS power scale (used by the log form's L1 term).
        bound: ``[num_pairs, num_beams]`` upper bound r̄ of each missing beam (normalised linear power),
            NaN where no bound applies (reported beams, beams absent from the data); a scalar tensor or
            float applies one bound (r_th) to every missing beam.
        floor: added to predictions before taking logs (normalised linear power).

    Returns:
        ``{"total", "fidelity", "sparsity", "penalty"}`` scalar tensors.
    """
    bound = torch.as_tensor(bound, dtype=pred.dtype, device=pred.device).expand_as(pred)
    observed = beam_mask & ~torch.isnan(rsrp)
    missing = beam_mask & torch.isnan(rsrp) & ~torch.isnan(bound)
    bound = torch.where(missing, bound, torch.ones_like(bound))
    num_pairs = max(pred.shape[0], 1)
    if fidelity == "shape":
        pred = pred * torch.pow(10.0, -pair_level(pred, rsrp, observed, floor))[:, None]
        fidelity = "log"
    if fidelity == "log":
        pred_b = torch.log10(pred + floor)
        rsrp_b = torch.log10(torch.where(observed, rsrp, torch.ones_like(rsrp)))
        err = pred_b - rsrp_b
        excess = torch.relu(pred_b - torch.log10(bound))
        l1 = (aps / x_scale[:, None]).sum()
    elif fidelity == "linear":
        err = pred - torch.nan_to_num(rsrp)
        excess = torch.relu(pred - bound)
        l1 = aps.sum()
    else:
        raise ValueError(f"unknown fidelity {fidelity!r}")
    fid = torch.where(observed, err.square(), torch.zeros_like(err)).sum() / num_pairs
    pen = torch.where(missing, excess.square(), torch.zeros_like(excess)).sum() / num_pairs
    sparsity = sparsity_weight * l1 / num_pairs
    total = fid + sparsity + penalty_weight * pen
    return {"total": total, "fidelity": fid, "sparsity": sparsity, "penalty": pen}


def log_errors(pred: torch.Tensor, rsrp: torch.Tensor, observed: torch.Tensor, floor: float = 1e-12) -> torch.Tensor:
    """log10(pred + floor) − log10(r) ``[num_pairs, num_beams]`` [bels] on the ``observed`` beams, 0 elsewhere."""
    err = torch.log10(pred + floor) - torch.log10(torch.where(observed, rsrp, torch.ones_like(rsrp)))
    return torch.where(observed, err, torch.zeros_like(err))


@torch.no_grad()
def pair_level(pred: torch.Tensor, rsrp: torch.Tensor, observed: torch.Tensor, floor: float = 1e-12) -> torch.Tensor:
    """Each pair's shrunk mean log error b = (1 − :data:`LEVEL_KEPT`) ē ``[num_pairs]`` [bels] over its
    ``observed [num_pairs, num_beams]`` beams (0 for a pair without any)."""
    err = log_errors(pred, rsrp, observed, floor)
    return (1.0 - LEVEL_KEPT) * err.sum(1) / observed.sum(1).clamp(min=1)


def mae_db(pred: torch.Tensor, rsrp: torch.Tensor, mask: torch.Tensor, floor: float = 1e-12) -> torch.Tensor:
    """Mean |10 log10(pred) − 10 log10(r)| [dB] over observed entries of ``mask`` (any consistent linear unit)."""
    observed = mask & ~torch.isnan(rsrp)
    if not bool(observed.any()):
        return torch.tensor(float("nan"))
    diff = 10.0 * (torch.log10(pred[observed] + floor) - torch.log10(rsrp[observed]))
    return diff.abs().mean()
