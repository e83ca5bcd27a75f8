"""The anchors pulled toward their cell's mean (empirical Bayes, :mod:`rflscm.models.rflscm.anchors`)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest
import torch
from test_corrections import data

from rflscm.models.rflscm.anchors import deviations, mean_noise, report_mean, shrunk_anchors
from rflscm.models.rflscm.config import CorrectionsConfig
from rflscm.models.rflscm.corrections import fit_corrections


def reports(
    cells: int, per_cell: int, tau: float, sigma: float, seed: int, most: int = 8
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(true level [P], residuals [P, most], mask [P, most], cell [P])``: each pair's true level error drawn about
    its cell's offset with spread ``tau``, 1 to ``most`` reports of it each off by Gaussian noise ``sigma`` [dB]."""
    gen = torch.Generator().manual_seed(seed)
    p = cells * per_cell
    cell = torch.arange(p) % cells
    offset = 3.0 * torch.randn(cells, generator=gen)
    level = offset[cell] + tau * torch.randn(p, generator=gen)
    count = torch.randint(1, most + 1, (p,), generator=gen)
    mask = torch.arange(most)[None, :] < count[:, None]
    resid = level[:, None] + sigma * torch.randn(p, most, generator=gen)
    return level, resid.double(), mask, cell


def means(resid: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return torch.as_tensor(np.nanmean(torch.where(mask, resid, torch.nan).numpy(), axis=1))


@pytest.mark.parametrize("tau,sigma", [(1.0, 3.0), (3.0, 2.0)])
def test_pooled_anchors_lie_closer_to_each_pairs_true_level_and_measure_the_noise_ratio(
    tau: float, sigma: float
) -> None:
    level, resid, mask, cell = reports(4, 600, tau, sigma, seed=1)
    own = means(resid, mask)
    count, pool = mask.sum(1), deviations(resid, mask)
    pooled, kappa = shrunk_anchors(own, count, pool, cell, torch.ones_like(cell, dtype=torch.bool))
    own_mse, pooled_mse = float((own - level).square().mean()), float((pooled - level).square().mean())
    assert pooled_mse < 0.9 * own_mse if tau < sigma else pooled_mse < own_mse
    # κ = σ²/τ²: measured from the anchors themselves
    assert kappa == pytest.approx(sigma**2 / tau**2, rel=0.4)


def test_a_pair_with_many_reports_keeps_its_anchor_and_ineligible_pairs_are_left_alone() -> None:
    level, resid, mask, cell = reports(2, 300, 1.0, 3.0, seed=2)
    mask[:10] = True
    resid[:10, :] = (
        level[:10, None].double() + 3.0 * torch.randn(10, 8, generator=torch.Generator().manual_seed(3)).double()
    )
    many = torch.cat([resid, level[:, None].double().expand(-1, 4000)], 1)  # pair 0..9: 4 008 reports at their level
    many_mask = torch.cat([mask, torch.zeros(len(level), 4000, dtype=torch.bool)], 1)
    many_mask[:10, 8:] = True
    own = means(many, many_mask)
    count, pool = many_mask.sum(1), deviations(many, many_mask)
    eligible = torch.ones(len(level), dtype=torch.bool)
    eligible[10:20] = False
    pooled, _ = shrunk_anchors(own, count, pool, cell, eligible)
    torch.testing.assert_close(pooled[:10], own[:10], atol=0.02, rtol=0)  # w ≈ 1
    torch.testing.assert_close(pooled[10:20], own[10:20], atol=0, rtol=0)  # not measured, not changed
    assert float((pooled[20:] - own[20:]).abs().max()) > 0.5  # the others moved


def test_anchors_of_pure_noise_pool_to_their_cells_mean() -> None:
    level, resid, mask, cell = reports(3, 500, 0.0, 3.0, seed=4)
    own = means(resid, mask)
    count, pool = mask.sum(1), deviations(resid, mask)
    pooled, kappa = shrunk_anchors(own, count, pool, cell, torch.ones_like(cell, dtype=torch.bool))
    about_cell = pooled - torch.stack([pooled[cell == c].mean() for c in range(3)])[cell]
    assert kappa > 20 and float(about_cell.std()) < 0.25 * float((own - level).std())
    for c in range(3):  # each cell's mean is what the pairs pool toward
        assert float(pooled[cell == c].mean()) == pytest.approx(float(level[cell == c].mean()), abs=0.3)


def test_where_nothing_measures_the_spreads_the_anchors_stay_their_own() -> None:
    anchor = torch.tensor([1.0, -2.0, 0.5])
    one = torch.ones(3, dtype=torch.long)
    everyone = torch.ones(3, dtype=torch.bool)
    noise = torch.randn(50, generator=torch.Generator().manual_seed(6))
    none = deviations(torch.zeros(3, 1), torch.ones(3, 1, dtype=torch.bool))
    assert none.numel() == 0  # a report each: no deviation to measure the noise on
    out, kappa = shrunk_anchors(anchor, one, none, torch.zeros(3), everyone)
    assert torch.equal(out, anchor) and math.isnan(kappa)
    out, kappa = shrunk_anchors(anchor, one * 5, noise, torch.arange(3), everyone)  # a pair per cell
    assert torch.equal(out, anchor) and math.isnan(kappa)
    out, kappa = shrunk_anchors(anchor, one * 5, noise, torch.zeros(3), ~everyone)  # none eligible
    assert torch.equal(out, anchor) and math.isnan(kappa)


def test_a_pairs_anchor_is_the_mean_of_its_reports_and_its_noise_sigma2_over_k() -> None:
    resid = torch.tensor([[1.0, 2.0, 6.0], [3.0, -9.0, 0.0], [0.0, 0.0, 0.0]], dtype=torch.float64)
    mask = torch.tensor([[True, True, True], [True, False, False], [False, False, False]])
    torch.testing.assert_close(report_mean(resid, mask), torch.tensor([3.0, 3.0, 0.0], dtype=torch.float64))
    gen = torch.Generator().manual_seed(7)
    pool = 2.0 * torch.randn(100_000, generator=gen)
    v = mean_noise(pool, torch.tensor([1, 4, 40]))
    torch.testing.assert_close(v, torch.tensor([4.0, 1.0, 0.1], dtype=torch.float64), rtol=0.03, atol=0)
    # the anchors the model computes have that variance: means of k draws of the same noise
    draws = 2.0 * torch.randn(20_000, 4, generator=gen, dtype=torch.float64)
    assert float(report_mean(draws, torch.ones_like(draws, dtype=torch.bool)).var()) == pytest.approx(1.0, rel=0.05)


def test_the_pass_pools_the_anchors_of_pairs_with_few_reports() -> None:
    """A field exact up to each pair's level error (τ = 1 dB) measured by 1–4 reports 3 dB off: the pass's anchors
    lie closer to the true level errors than each pair's own mean, and the pass reports κ."""
    level, resid, mask, cell = reports(2, 400, 1.0, 3.0, seed=5, most=4)
    rsrp = torch.where(mask, torch.pow(10.0, resid / 10.0), torch.nan).float()  # the prediction is 1 on every beam
    p, m = rsrp.shape
    pairs = data(rsrp.tolist(), cell.tolist())  # grid ids 100, 101, …

    def render(at: torch.Tensor):
        bins = torch.zeros(len(at), 1, dtype=torch.long)
        return bins, torch.ones(len(at), 1), torch.ones(len(at), m)

    def columns(cells: torch.Tensor, bins: torch.Tensor) -> torch.Tensor:
        return torch.ones(len(cells), m, bins.shape[1])

    cfg = CorrectionsConfig(pair_posterior=False, calibrate_levels=False)
    fitted = fit_corrections(cfg, pairs, m // 2, np.array([7, 8]), render, columns, seed=0)
    assert fitted.anchors is not None and math.isfinite(fitted.anchor_kappa)
    index = pd.MultiIndex.from_arrays(
        [np.array([7, 8])[cell.numpy()], 100 + np.arange(p)], names=["cell_id", "grid_id"]
    )
    pooled = torch.as_tensor(fitted.anchors.reindex(index).to_numpy().copy())
    own = means(resid, mask)
    assert float((pooled - level).square().mean()) < 0.8 * float((own - level).square().mean())
