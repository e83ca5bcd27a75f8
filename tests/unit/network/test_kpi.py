"""Network KPIs against hand-computed values on a two-cell toy."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rflscm.errors import ConfigError
from rflscm.network.kpi import KPIConfig, best_beam_power_from_rsrp, network_kpis


def dbm(mw: float) -> float:
    return 10 * math.log10(mw)


def test_noise_per_resource_element() -> None:
    cfg = KPIConfig(noise_figure_db=7.0)
    assert cfg.noise_per_re_dbm(3.5e9) == pytest.approx(-174 + 10 * math.log10(30e3) + 7)  # −122.23 dBm
    assert cfg.noise_per_re_dbm(2.1e9) == pytest.approx(-174 + 10 * math.log10(15e3) + 7)  # −125.24 dBm
    assert cfg.noise_per_re_dbm(3.5e9) == pytest.approx(-122.229, abs=1e-3)
    d = cfg.describe([3.5e9])["carriers"]["3.5 GHz"]
    assert d["noise_ssb_bw_dbm"] == pytest.approx(-174 + 10 * math.log10(240 * 30e3) + 7, abs=0.01)  # 7.2 MHz


def test_two_cell_toy_by_hand() -> None:
    # two cells on 3.5 GHz, three grids [mW]: grid 0 cell 0 strong; grid 1 both weak; grid 2 both within 3 dB
    p = np.array([[1e-9, 1e-11, 1e-10], [1e-10, 2e-12, 5e-11]])
    cfg = KPIConfig(threshold_dbm=-105.0, noise_figure_db=7.0, overlap_servers=2, overlap_db=6.0)
    k = network_kpis(p, np.array([3.5e9, 3.5e9]), cfg)
    n = 10 ** ((-174 + 10 * math.log10(30e3) + 7) / 10)
    sinr = [1e-9 / (1e-10 + n), 1e-11 / (2e-12 + n), 1e-10 / (5e-11 + n)]
    assert k["coverage"] == pytest.approx(2 / 3)  # −90 and −100 dBm covered, −110 dBm not
    assert k["mean_sinr_db"] == pytest.approx(np.mean([dbm(s) for s in sinr]))
    assert k["overlap"] == pytest.approx(1 / 3)  # only grid 2 has a second cell within 6 dB
    assert k["mean_rsrp_dbm"] == pytest.approx(np.mean([-90.0, -110.0, -100.0]))
    assert k["p5_sinr_db"] == pytest.approx(np.quantile([dbm(s) for s in sinr], 0.05))


def test_carriers_do_not_interfere_and_unknown_pairs_drop_out() -> None:
    p = np.array([[1e-10, 1e-10], [1e-9, 1e-9]])  # cell 1 on another carrier: no interference
    k = network_kpis(p, np.array([3.5e9, 2.1e9]), KPIConfig())
    n35 = 10 ** (KPIConfig().noise_per_re_dbm(3.5e9) / 10)
    assert k["per_carrier"]["3.5 GHz"]["mean_sinr_db"] == pytest.approx(dbm(1e-10 / n35))
    assert k["num_samples"] == 4
    known = np.array([[True, False], [True, True]])
    k2 = network_kpis(p, np.array([3.5e9, 2.1e9]), KPIConfig(), known)
    assert k2["num_samples"] == 3  # grid 1 has no known pair on 3.5 GHz


def test_grids_without_signal_are_floored_not_minus_infinity() -> None:
    p = np.array([[1e-10, 0.0]])  # grid 1: no path at all
    k = network_kpis(p, np.array([3.5e9]), KPIConfig())
    n = 10 ** (KPIConfig().noise_per_re_dbm(3.5e9) / 10)
    assert k["no_signal"] == 0.5 and k["coverage"] == 0.5
    assert k["mean_rsrp_dbm"] == pytest.approx((-100.0 - 156.0) / 2)
    assert k["mean_sinr_db"] == pytest.approx((dbm(1e-10 / n) - 30.0) / 2)


def test_power_from_rsrp_table() -> None:
    rsrp = np.array([[-90.0, -95.0, np.nan], [-300.0, np.nan, np.nan]])
    power, known = best_beam_power_from_rsrp(
        rsrp, np.array([11, 12]), np.array([101, 100]), np.array([11, 12]), np.array([100, 101])
    )
    assert power[0, 1] == pytest.approx(1e-9) and known[0, 1] and not known[0, 0]
    k = network_kpis(power, np.array([3.5e9, 3.5e9]), KPIConfig(overlap_servers=2), known)
    assert k["overlap"] == 0.0  # the −300 dBm floor of a prediction is no signal, not a second server


def test_bad_kpi_constants() -> None:
    with pytest.raises(ConfigError, match="overlap_servers"):
        KPIConfig(overlap_servers=1)


def test_objectives() -> None:
    import torch

    from rflscm.network.search import objective_value

    k = {
        "coverage": torch.tensor(0.5),
        "margin": torch.tensor(1.0),
        "num_samples": torch.tensor(100.0),
        "mean_sinr_clipped_db": torch.tensor(4.0),
    }
    assert float(objective_value(k, "coverage")) == pytest.approx(0.5 + 0.004)  # tie-break < one sample (0.01)
    assert float(objective_value(k, "sinr")) == pytest.approx(4.0)
    assert float(objective_value(k, "weighted")) == pytest.approx(0.5 + 0.1 * 0.4)
    with pytest.raises(ConfigError, match="--objective"):
        objective_value(k, "throughput")
