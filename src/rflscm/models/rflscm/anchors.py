"""Each pair's anchor as an estimate from few noisy reports: pulled toward its cell's mean (empirical Bayes).

A pair's anchor is the median error left on its own reported round-1 beams after the cell's level
(:mod:`.corrections`).  With top-N or SS-SINR reports a pair has a handful of beams, each off by the
fading, the report's error and the field's shape, so its median is a noisy estimate of the pair's true
level error.  Across a cell's pairs the anchors spread by the true level errors *and* by that noise.  The
two are told apart from the data themselves (the method of moments):

* the noise a median of k reports carries, v_k, is measured by drawing k of the pooled residuals (each about
  its pair's mean) many times: a median of few reports is noisier than their mean by an amount that depends
  on the noise's tails, which the fading and the report errors make heavy;
* the true level errors' spread, τ², is what the anchors spread about their cell's mean beyond that noise;

and a pair's anchor becomes ``m̄_c + w (m − m̄_c)`` with ``w = τ² / (τ² + v_k)``: a pair with many reports
keeps its own anchor, one with a single report leans on its cell.  No parameter: v_k and τ² are measured on
the anchors being pulled (docs/DECISIONS.md, "Anchors pulled toward their cell's mean").
"""

from __future__ import annotations

import math

import torch

DRAWS = 4096
"""Medians drawn per report count to measure the noise a k-report median carries (seeded: a pass is deterministic)."""
POOL = 200_000
"""At most this many residuals are pooled for those draws (an even spread of them beyond)."""


def deviations(resid: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Deviations ``[D]`` [dB]: the residuals ``resid [B, M]`` on the reports ``mask [B, M]`` of every pair with two
    or more, each about its pair's mean and scaled by √(k/(k − 1)) so that they spread as the reports' noise does
    (flattened, float32)."""
    count = mask.sum(1)
    r = torch.where(mask, resid.double(), 0.0)
    mean = r.sum(1) / count.clamp_min(1)
    scale = torch.sqrt(count / (count - 1).clamp_min(1)).double()
    dev = (resid.double() - mean[:, None]) * scale[:, None]
    return dev[mask & (count >= 2)[:, None]].float()


def median_noise(pool: torch.Tensor, counts: torch.Tensor) -> dict[int, float]:
    """Variance [dB²] of the median of k reports drawn from the pooled noise ``pool [D]``, for each k of ``counts``:
    the median of few reports is noisier than their mean by a factor that depends on the noise's tails."""
    if pool.numel() > POOL:
        pool = pool[torch.linspace(0, pool.numel() - 1, POOL).long()]
    gen = torch.Generator().manual_seed(0)
    out = {}
    for k in sorted({int(c) for c in counts.tolist()}):
        draws = pool[torch.randint(pool.numel(), (DRAWS, k), generator=gen)].double()
        out[k] = float(torch.quantile(draws, 0.5, dim=1).var())
    return out


def shrunk_anchors(
    anchor: torch.Tensor, count: torch.Tensor, pool: torch.Tensor, cell: torch.Tensor, eligible: torch.Tensor
) -> tuple[torch.Tensor, float]:
    """Anchors ``[P]`` [dB] pulled toward their cell's mean, and κ = σ²/τ² (∞: pooled whole; NaN: left alone).

    Args:
        anchor: each pair's anchor [dB] (the median of its residuals).
        count: its number of reports ``[P]``.
        pool: the eligible pairs' residual deviations ``[D]`` [dB] (:func:`deviations`): the reports' noise.
        cell: its cell index ``[P]``.
        eligible: bool ``[P]``, the pairs whose anchor is their whole correction (no posterior fitted on it);
            only these are measured and changed.

    A pair's anchor m becomes ``m̄_c + w (m − m̄_c)``, ``w = τ² / (τ² + v_k)``: v_k the variance of a k-report median
    of the pooled noise (:func:`median_noise`), τ² the anchors' spread about their cell's mean less the mean v_k.
    Where the data cannot measure the two (fewer than two deviations, no cell with two eligible pairs) the anchors
    are returned unchanged.
    """
    out = anchor.clone()
    on = eligible & (count > 0) & torch.isfinite(anchor)
    if not bool(on.any()) or pool.numel() < 2:
        return out, math.nan
    m, k, c = anchor[on].double(), count[on].long(), cell[on].long()
    cells, c = torch.unique(c, return_inverse=True)
    n = torch.bincount(c, minlength=cells.numel()).double()
    shared = n[c] > 1  # a cell's only eligible pair is its own mean: it says nothing about the spread
    if int(shared.sum()) <= int((n > 1).sum()):
        return out, math.nan
    centre = torch.bincount(c, weights=m, minlength=cells.numel()) / n
    noise = median_noise(pool, k)
    v = torch.tensor([noise[int(j)] for j in k.tolist()], dtype=torch.float64)
    dev = m - centre[c]
    between = float(dev[shared].square().sum()) / (int(shared.sum()) - int((n > 1).sum()))
    tau2 = max(between - float(v[shared].mean()), 0.0)
    weight = tau2 / (tau2 + v) if tau2 > 0 else torch.zeros_like(v)
    out[on] = (centre[c] + weight * dev).to(out.dtype)
    sigma2 = float(pool.double().square().mean())
    return out, (sigma2 / tau2 if tau2 > 0 else math.inf)
