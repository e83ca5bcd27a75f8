import numpy as np
import pytest
import torch

from rflscm.errors import ConfigError
from rflscm.geometry import AngleGrid, engineering_to_internal, internal_to_engineering, unit_vectors
from rflscm.geometry.angles import angles_of, rotation_matrix


def test_engineering_convention_examples():
    # North (0° clockwise from north) is 90° CCW from east; 90° (east) is 0°; tilt down is negative elevation.
    el, az = engineering_to_internal(np.array([0.0, 90.0, 180.0, 270.0]), np.array([10.0, 0.0, -5.0, 0.0]))
    np.testing.assert_allclose(np.rad2deg(az), [90.0, 0.0, 270.0, 180.0], atol=1e-12)
    np.testing.assert_allclose(np.rad2deg(el), [-10.0, 0.0, 5.0, 0.0], atol=1e-12)


def test_angle_converter_round_trip():
    rng = np.random.default_rng(1)
    azimuth_deg, tilt_deg = rng.uniform(0, 360, 100), rng.uniform(-90, 90, 100)
    back_az, back_tilt = internal_to_engineering(*engineering_to_internal(azimuth_deg, tilt_deg))
    np.testing.assert_allclose(back_az, azimuth_deg, atol=1e-9)
    np.testing.assert_allclose(back_tilt, tilt_deg, atol=1e-9)


def test_unit_vectors_and_angles_round_trip():
    el = torch.tensor([0.0, 0.3, -1.2, 1.5], dtype=torch.float64)
    az = torch.tensor([0.0, 2.0, 4.0, 6.0], dtype=torch.float64)
    v = unit_vectors(el, az)
    torch.testing.assert_close(v.norm(dim=-1), torch.ones(4, dtype=torch.float64))
    el2, az2 = angles_of(v)
    torch.testing.assert_close(el2, el)
    torch.testing.assert_close(az2, az)


def test_rotation_tilts_boresight_down_and_turns_ccw():
    r = rotation_matrix(np.deg2rad(90.0), np.deg2rad(10.0))
    boresight = r @ np.array([1.0, 0.0, 0.0])
    np.testing.assert_allclose(boresight, [0.0, np.cos(np.deg2rad(10)), -np.sin(np.deg2rad(10))], atol=1e-12)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)


def test_default_grid_covers_the_sphere():
    g = AngleGrid()
    assert g.shape == (91, 72) and g.num_bins == 6552
    assert np.rad2deg(g.elevations_rad[[0, -1]]).tolist() == pytest.approx([-90.0, 90.0])
    assert g.az_step_deg == 5.0


def test_bin_of_recovers_bin_centres_and_wraps_azimuth():
    g = AngleGrid()
    el, az = g.bin_angles()
    np.testing.assert_array_equal(g.bin_of(el, az), np.arange(g.num_bins))
    # 359° is nearest to the 0° bin; a slight offset stays in the same bin.
    assert g.bin_of(np.array([0.0]), np.deg2rad([359.0]))[0] == g.bin_of(np.array([0.0]), np.array([0.0]))[0]
    n = g.bin_of(np.deg2rad([10.9]), np.deg2rad([47.4]))[0]
    assert divmod(int(n), g.num_az) == (50, 9)


def test_bin_of_vectors_matches_bin_of():
    g = AngleGrid(num_el=19, num_az=24, el_min_deg=-90, el_step_deg=10)
    v = torch.randn(50, 3, dtype=torch.float64)
    el, az = angles_of(v)
    np.testing.assert_array_equal(g.bin_of_vectors(v).numpy(), g.bin_of(el.numpy(), az.numpy()))


def test_grid_rejects_bad_ranges():
    with pytest.raises(ConfigError):
        AngleGrid(num_el=91, el_min_deg=-90, el_step_deg=3.0)
    with pytest.raises(ConfigError):
        AngleGrid(num_el=0)


def test_coarse_mapping_blocks_and_partial_edges():
    g = AngleGrid(num_el=7, num_az=8, el_min_deg=-90, el_step_deg=30)
    cm = g.coarse(3)
    assert (cm.num_el, cm.num_az) == (3, 3)
    # Coarse (2, 2) covers fine elevation 6 only and azimuths 6, 7: a 1 × 2 partial block.
    fine, valid = cm.children(torch.tensor([2 * 3 + 2]))
    assert valid.sum().item() == 2
    assert sorted(fine[valid].tolist()) == [6 * 8 + 6, 6 * 8 + 7]
    # Every fine bin belongs to exactly one coarse block, and parent_of agrees with children.
    all_fine, all_valid = cm.children(torch.arange(cm.num_bins))
    listed = all_fine[all_valid]
    assert sorted(listed.tolist()) == list(range(g.num_bins))
    parents = torch.arange(cm.num_bins)[:, None].expand_as(all_fine)[all_valid]
    torch.testing.assert_close(cm.parent_of()[listed], parents)
    # Representatives are every beta-th bin on both axes.
    assert cm.representative_bins().tolist() == [i * 3 * 8 + j * 3 for i in range(3) for j in range(3)]
