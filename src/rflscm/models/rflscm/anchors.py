"""Each pair's anchor as an estimate from few noisy reports: pulled toward its cell's mean (empirical Bayes).

A pair's anchor is the mean error [dB] left on its own reported round-1 beams after the cell's level
(:mod:`.corrections`, :func:`report_mean`).  With top-N or SS-SINR reports a pair has a handful of beams, each off
by the fading, the report's error and the field's shape, so its mean is a noisy estimate of the pair's true
level error.  Across a cell's pairs the anchors spread by the true level errors *and* by that noise.  The
two are told apart from the data themselves (the method of moments):

* the noise a mean of k reports carries, v_k = σ²/k, σ² the variance of the pooled residuals, each about its
  pair's mean (:func:`deviations`);
* the true level errors' spread, τ², is what the anchors spread about their cell's mean beyond that noise;

and a pair's anchor becomes ``m̄_c + w (m − m̄_c)`` with ``w = τ² / (τ² + v_k)``: a pair with many reports
keeps its own anchor, one with a single report leans on its cell.  No parameter: v_k and τ² are measured on
the anchors being pulled (docs/DECISIONS.md, "Anchors pulled toward their cell's mean").
"""

from __future__ import annotations

import math

import torch


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


def report_mean(resid: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Each pair's anchor ``[P]`` [dB]: the mean of its residuals ``resid [P, M]`` [dB] on its reports ``mask [P, M]``
    (0 for a pair without any).  The mean, not the median: the reports' errors are near-Gaussian in dB, and the
    median of the same reports scored round 2 0.00–0.03 dB worse on every row (docs/DECISIONS.md, "The anchor is
    its reports' mean")."""
    r = torch.where(mask, resid, torch.zeros_like(resid))
    return r.sum(1) / mask.sum(1).clamp_min(1).to(r.dtype)


def mean_noise(pool: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """Variance [dB²] of the mean of k reports of the pooled noise ``pool [D]``, σ²/k, for each of ``counts [P]``."""
    sigma2 = float(pool.double().square().mean()) if pool.numel() else 0.0
    return sigma2 / counts.double().clamp_min(1)


def shrunk_anchors(
    anchor: torch.Tensor, count: torch.Tensor, pool: torch.Tensor, cell: torch.Tensor, eligible: torch.Tensor
) -> tuple[torch.Tensor, float]:
    """Anchors ``[P]`` [dB] pulled toward their cell's mean, and κ = σ²/τ² (∞: pooled whole; NaN: left alone).

    Args:
        anchor: each pair's anchor [dB] (the mean of its residuals, :func:`report_mean`).
        count: its number of reports ``[P]``.
        pool: the eligible pairs' residual deviations ``[D]`` [dB] (:func:`deviations`): the reports' noise.
        cell: its cell index ``[P]``.
        eligible: bool ``[P]``, the pairs whose anchor is their whole correction (no posterior fitted on it);
            only these are measured and changed.

    A pair's anchor m becomes ``m̄_c + w (m − m̄_c)``, ``w = τ² / (τ² + v_k)``: v_k the variance of a k-report mean
    of the pooled noise (:func:`mean_noise`), τ² the anchors' spread about their cell's mean less the mean v_k.
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
    v = mean_noise(pool, k)
    dev = m - centre[c]
    between = float(dev[shared].square().sum()) / (int(shared.sum()) - int((n > 1).sum()))
    tau2 = max(between - float(v[shared].mean()), 0.0)
    weight = tau2 / (tau2 + v) if tau2 > 0 else torch.zeros_like(v)
    out[on] = (centre[c] + weight * dev).to(out.dtype)
    sigma2 = float(pool.double().square().mean())
    return out, (sigma2 / tau2 if tau2 > 0 else math.inf)
