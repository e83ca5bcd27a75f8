"""Measurement model: noise statistics, quantisation, threshold, clipping, reported pairs."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from rflscm.errors import ConfigError
from rflscm.sim.noise import MeasurementModel, measure


def test_noise_std_matches_sigma_and_is_unbiased() -> None:
    rng = np.random.default_rng(1)
    clean = np.full(200_000, -90.0)
    noisy = MeasurementModel(sigma_db=2.0, quantization_db=0.0).apply(clean, rng)
    assert np.std(noisy - clean) == pytest.approx(2.0, rel=0.01)
    assert np.mean(noisy - clean) == pytest.approx(0.0, abs=0.02)
    quantised = MeasurementModel(sigma_db=3.0).apply(clean, np.random.default_rng(2))
    assert np.std(quantised - clean) == pytest.approx(np.sqrt(9.0 + 1 / 12), rel=0.01)  # + uniform rounding error


def test_values_are_quantised_thresholded_and_clipped() -> None:
    rng = np.random.default_rng(3)
    clean = np.concatenate([rng.uniform(-140, -100, 10_000), [-20.0, -np.inf, -119.6, -120.4, -120.5]])
    model = MeasurementModel(sigma_db=0.0, threshold_dbm=-120.0)
    out = model.apply(clean, rng)
    finite = np.isfinite(out)
    assert np.all(out[finite] == np.round(out[finite]))  # 1 dB steps: integers
    assert np.all(out[finite] >= -120.0) and np.all(out[finite] <= -31.0)
    assert out[-5] == -31.0  # saturates at the top of the reportable range
    assert np.isnan(out[-4])  # no path: never reported
    assert out[-3] == -120.0 and out[-2] == -120.0  # rounds to the threshold: reported
    assert out[-1] == -120.0  # −120.5 rounds half to even (−120): reported
    np.testing.assert_array_equal(np.isnan(out[:-5]), np.round(clean[:-5]) < -120.0)


def test_same_seed_same_noise() -> None:
    clean = np.linspace(-130, -60, 500)
    a = MeasurementModel().apply(clean, np.random.default_rng(9))
    b = MeasurementModel().apply(clean, np.random.default_rng(9))
    c = MeasurementModel().apply(clean, np.random.default_rng(10))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(np.nan_to_num(a), np.nan_to_num(c))


def test_measure_keeps_pairs_with_a_reported_beam_and_all_their_beams() -> None:
    rows = []
    for grid, levels in ((1, [-80.0, -150.0, -150.0]), (2, [-150.0, -150.0, -150.0]), (3, [-150.0, -150.0, -85.0])):
        for beam, level in enumerate(levels):
            rows.append((1, 10, grid, "ssb", beam, level))
    rows.append((1, 10, 3, "csi", 0, -150.0))
    noiseless = pd.DataFrame(rows, columns=["round", "cell_id", "grid_id", "beam_type", "beam_id", "rsrp_dbm"])
    out = measure(noiseless, MeasurementModel(sigma_db=0.5), np.random.default_rng(0))
    assert sorted(out["grid_id"].unique()) == [1, 3]  # grid 2: no beam above threshold, pair dropped
    assert len(out) == 7  # 3 + 3 SSB rows + the CSI row of grid 3
    assert out["rsrp_dbm"].notna().sum() == 2


def test_cells_are_detected_by_their_ssb() -> None:
    rows = [
        (1, 10, 1, "ssb", 0, -150.0),
        (1, 10, 1, "csi", 0, -80.0),
        (1, 10, 2, "ssb", 0, -90.0),
        (1, 10, 2, "csi", 0, -150.0),
    ]
    noiseless = pd.DataFrame(rows, columns=["round", "cell_id", "grid_id", "beam_type", "beam_id", "rsrp_dbm"])
    by_ssb = measure(noiseless, MeasurementModel(sigma_db=0.5), np.random.default_rng(0))
    assert by_ssb["grid_id"].tolist() == [2, 2]  # grid 1: only a CSI-RS beam is strong, the cell is not found
    by_any = measure(noiseless, MeasurementModel(sigma_db=0.5), np.random.default_rng(0), detect_on=None)
    assert sorted(by_any["grid_id"].unique()) == [1, 2]


def test_invalid_model_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="reportable range"):
        MeasurementModel(threshold_dbm=0.0)
    with pytest.raises(ConfigError, match=">= 0 dB"):
        MeasurementModel(sigma_db=-1.0)
