"""Physics of the element pattern, codebooks and the sensing matrix."""

import numpy as np
import pytest
import torch

from rflscm.antenna import (
    ArrayGeometry,
    CellAntenna,
    DFTCodebook,
    MeasuredElement,
    SSBCodebook,
    TR38901Element,
    codebook_from_dict,
    sensing_matrix,
    wavelength_of,
)
from rflscm.errors import ConfigError
from rflscm.geometry import AngleGrid, engineering_to_internal

GRID = AngleGrid()
WL = wavelength_of(3.5e9)
# Flat over the front half-space, 40 dB down behind: only the array shapes the beam, without the
# front/back mirror lobe that a planar array of truly isotropic elements has.
ISOTROPIC = MeasuredElement(max_gain_dbi=0.0, horizontal_loss_db=(0.0, 0.0, 40.0, 0.0), vertical_loss_db=(0.0,) * 4)


def _peak_angles_deg(a: torch.Tensor, grid: AngleGrid) -> tuple[np.ndarray, np.ndarray]:
    el, az = grid.bin_angles()
    idx = a.argmax(dim=1).numpy()
    return np.rad2deg(el[idx]), np.rad2deg(az[idx])


def _circular_diff_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs((a - b + 180.0) % 360.0 - 180.0)


def test_tr38901_element_peak_and_limits():
    e = TR38901Element()
    boresight = torch.tensor([[1.0, 0.0, 0.0]])
    assert e.gain_db(boresight).item() == pytest.approx(8.0)
    # 3 dB down at half the HPBW in azimuth (Table 7.3-1: 12 (φ/φ3dB)² at φ = 32.5° → 3 dB).
    phi = np.deg2rad(32.5)
    assert e.gain_db(torch.tensor([[np.cos(phi), np.sin(phi), 0.0]])).item() == pytest.approx(5.0)
    back = torch.tensor([[-1.0, 0.0, 0.0]])
    assert e.gain_db(back).item() == pytest.approx(8.0 - 30.0)


@pytest.mark.parametrize("azimuth_deg", [0.0, 37.0, 200.0])
@pytest.mark.parametrize("mech_tilt_deg", [0.0, 6.0])
def test_beam_peak_lies_in_steering_direction(azimuth_deg, mech_tilt_deg):
    # Narrow (full-array) beams steered around boresight; isotropic elements so only the array steers.
    cb = SSBCodebook(azimuths_deg=(-20.0, 0.0, 25.0), tilts_deg=(0.0, 8.0), active_h=8, active_v=4)
    ant = CellAntenna(azimuth_deg=azimuth_deg, mech_tilt_deg=mech_tilt_deg, element=ISOTROPIC)
    a = sensing_matrix(ant, cb, GRID, WL, dtype=torch.float64)
    peak_el, peak_az = _peak_angles_deg(a, GRID)
    # Expected world direction of each beam: local steering rotated by the antenna.
    tilt, az = np.meshgrid(np.deg2rad(cb.tilts_deg), np.deg2rad(cb.azimuths_deg), indexing="ij")
    local = np.stack((np.cos(-tilt) * np.cos(az), np.cos(-tilt) * np.sin(az), np.sin(-tilt)), -1).reshape(-1, 3)
    world = local @ ant.rotation().T
    exp_el = np.rad2deg(np.arcsin(world[:, 2]))
    exp_az = np.rad2deg(np.arctan2(world[:, 1], world[:, 0])) % 360
    assert np.all(np.abs(peak_el - exp_el) <= GRID.el_step_deg)
    assert np.all(_circular_diff_deg(peak_az, exp_az) <= GRID.az_step_deg)


def test_electrical_tilt_moves_main_lobe_by_the_tilt():
    cb = SSBCodebook(azimuths_deg=(0.0,), tilts_deg=(0.0,), active_h=8, active_v=4)
    grid = AngleGrid(num_el=181, num_az=72, el_min_deg=-90.0, el_step_deg=1.0)
    for etilt in (0.0, 6.0, 12.0):
        ant = CellAntenna(azimuth_deg=90.0, elec_tilt_deg=etilt, element=ISOTROPIC)
        peak_el, peak_az = _peak_angles_deg(sensing_matrix(ant, cb, grid, WL, dtype=torch.float64), grid)
        assert peak_el[0] == pytest.approx(-etilt, abs=1.0)
        assert peak_az[0] == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("codebook", [SSBCodebook(), DFTCodebook()])
def test_sensing_matrix_is_nonnegative_and_bounded(codebook):
    ant = CellAntenna(azimuth_deg=123.0, mech_tilt_deg=4.0, elec_tilt_deg=3.0)
    a = sensing_matrix(ant, codebook, GRID, WL, dtype=torch.float64)
    assert a.shape == (codebook.num_beams, GRID.num_bins)
    assert torch.all(a >= 0)
    bound = ant.tx_power_mw * ant.element.peak_gain_lin * ant.array.num_elements
    assert a.max().item() <= bound * (1 + 1e-9)
    # Unit-power beams: the peak reaches a large share of the coherent bound for a full-array DFT beam.
    if isinstance(codebook, DFTCodebook):
        assert a.max().item() > 0.5 * bound


@pytest.mark.parametrize("k", [1, 5, -3])
def test_azimuth_rotation_equals_column_shift(k):
    # The paper's "method b": turning the antenna by k azimuth bins shifts A's columns by k bins.
    base = CellAntenna(azimuth_deg=30.0, mech_tilt_deg=5.0, elec_tilt_deg=2.0)
    turned = base.rotated(d_azimuth_deg=k * GRID.az_step_deg)
    a0 = sensing_matrix(base, DFTCodebook(), GRID, WL, dtype=torch.float64).reshape(-1, GRID.num_el, GRID.num_az)
    a1 = sensing_matrix(turned, DFTCodebook(), GRID, WL, dtype=torch.float64).reshape(-1, GRID.num_el, GRID.num_az)
    # Clockwise (engineering) azimuth is negative in the code's CCW azimuth, hence the minus sign.
    torch.testing.assert_close(a1, torch.roll(a0, shifts=-k, dims=2), rtol=1e-9, atol=1e-12)


def test_higher_carrier_narrows_main_lobe():
    array = ArrayGeometry.for_frequency(2.1e9)
    cb = SSBCodebook(azimuths_deg=(0.0,), tilts_deg=(0.0,), active_h=8, active_v=4)
    grid = AngleGrid(num_el=1, num_az=720, el_min_deg=0.0, el_step_deg=1.0)
    ant = CellAntenna(azimuth_deg=90.0, array=array, element=ISOTROPIC)

    def half_power_width(freq_hz: float) -> int:
        a = sensing_matrix(ant, cb, grid, wavelength_of(freq_hz), dtype=torch.float64)[0]
        return int((a >= a.max() / 2).sum())

    assert half_power_width(3.5e9) < half_power_width(2.1e9)


def test_float32_matches_float64_and_directions_list_matches_grid():
    ant = CellAntenna(azimuth_deg=300.0, mech_tilt_deg=3.0)
    a64 = sensing_matrix(ant, DFTCodebook(), GRID, WL, dtype=torch.float64)
    a32 = sensing_matrix(ant, DFTCodebook(), GRID, WL, dtype=torch.float32)
    torch.testing.assert_close(a32.double(), a64, rtol=2e-3, atol=1e-6 * a64.max().item())
    cols = torch.tensor([0, 17, 4000, 6551])
    sub = sensing_matrix(ant, DFTCodebook(), GRID.directions(torch.float64)[cols], WL, dtype=torch.float64)
    torch.testing.assert_close(sub, a64[:, cols])


def test_codebook_from_dict_and_errors():
    cb = codebook_from_dict({"type": "dft", "o1": 4, "beams_h": [0, 1]})
    assert isinstance(cb, DFTCodebook) and cb.num_beams == 2 * 4
    with pytest.raises(ConfigError, match="type"):
        codebook_from_dict({"type": "butler"})
    with pytest.raises(ConfigError, match="unknown key"):
        codebook_from_dict({"type": "ssb", "beams": 8})
    with pytest.raises(ConfigError, match="does not match"):
        sensing_matrix(CellAntenna(array=ArrayGeometry(num_h=4, num_v=4)), DFTCodebook(), GRID, WL)


def test_default_csi_beams_point_inside_the_sector():
    ant = CellAntenna(azimuth_deg=90.0)
    a = sensing_matrix(ant, DFTCodebook(), GRID, WL)
    el_deg, az_deg = _peak_angles_deg(a, GRID)
    off = _circular_diff_deg(az_deg, np.rad2deg(engineering_to_internal(90.0, 0.0)[1]))
    assert np.all(off <= 65.0) and np.all(el_deg <= 0.0)
