"""Procedural city: geometry, Fresnel coefficients, penetration, image-method paths vs independent formulas."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from rflscm.errors import ConfigError
from rflscm.sim.backend import PATH_COLUMNS, SceneBackend
from rflscm.sim.procedural import (
    MATERIALS,
    Material,
    ProceduralCity,
    fresnel_coefficients,
    reflection_power,
    segment_box_overlap,
    wall_loss_db,
)

C = 299_792_458.0


def friis(length_m: np.ndarray, freq_hz: float) -> np.ndarray:
    return (C / freq_hz / (4 * np.pi * np.asarray(length_m))) ** 2


def eta_of(name: str, freq_hz: float) -> complex:
    # ITU-R P.2040-1: eps' = a f^b, sigma = c f^d, eta = eps' - j sigma / (2 pi f eps0)
    m = MATERIALS[name]
    f = freq_hz / 1e9
    return m.a * f**m.b - 1j * (m.c * f**m.d) / (2 * np.pi * freq_hz * 8.8541878128e-12)


def r_te(theta: float, eta: complex) -> complex:
    s = np.sqrt(eta - np.sin(theta) ** 2 + 0j)
    return (np.cos(theta) - s) / (np.cos(theta) + s)


def r_tm(theta: float, eta: complex) -> complex:
    s = np.sqrt(eta - np.sin(theta) ** 2 + 0j)
    return (eta * np.cos(theta) - s) / (eta * np.cos(theta) + s)


def test_is_a_scene_backend_and_layout_is_deterministic_by_seed() -> None:
    a, b, c = ProceduralCity(seed=3), ProceduralCity(seed=3), ProceduralCity(seed=4)
    assert isinstance(a, SceneBackend)
    assert a.num_buildings > 20
    np.testing.assert_array_equal(a.box_lo, b.box_lo)
    assert not np.array_equal(a.box_lo, c.box_lo)
    roofs = a.rooftops()
    assert roofs.shape == (a.num_buildings, 3)
    assert not a.is_outdoor(roofs[:, :2]).any()
    lo, hi = a.bounds()
    assert hi[2] == pytest.approx(a.box_hi[:, 2].max()) and lo[2] == 0.0


def test_buildings_keep_street_gaps() -> None:
    city = ProceduralCity(seed=1, street_m=12.0)
    lo, hi = city.box_lo, city.box_hi
    for i in range(city.num_buildings):
        for j in range(i):
            gap = np.maximum(lo[i, :2] - hi[j, :2], lo[j, :2] - hi[i, :2]).max()
            assert gap >= 12.0 - 1e-9


def test_permittivity_matches_p2040() -> None:
    for name in ("concrete", "medium_dry_ground"):
        got = MATERIALS[name].permittivity(3.5e9)
        assert got == pytest.approx(eta_of(name, 3.5e9), rel=1e-3)


@pytest.mark.parametrize("name", sorted(MATERIALS))
@pytest.mark.parametrize("freq_hz", [0.7e9, 2.1e9, 3.5e9, 28e9])
def test_fresnel_magnitude_at_most_one_and_limits(name: str, freq_hz: float) -> None:
    eta = MATERIALS[name].permittivity(freq_hz)
    theta = np.linspace(0.0, np.pi / 2, 181)
    te, tm = fresnel_coefficients(np.cos(theta), eta)
    assert np.all(np.abs(te) <= 1 + 1e-12) and np.all(np.abs(tm) <= 1 + 1e-12)
    normal = (1 - np.sqrt(eta)) / (1 + np.sqrt(eta))
    assert abs(te[0]) == pytest.approx(abs(normal), rel=1e-9) and abs(tm[0]) == pytest.approx(abs(normal), rel=1e-9)
    assert abs(te[-1]) == pytest.approx(1.0, abs=1e-6) and abs(tm[-1]) == pytest.approx(1.0, abs=1e-6)
    np.testing.assert_allclose(te[45], r_te(theta[45], eta), rtol=1e-9)
    np.testing.assert_allclose(tm[45], r_tm(theta[45], eta), rtol=1e-9)


def test_tm_has_a_brewster_dip_on_lossless_media() -> None:
    eps = 5.0
    lossless = Material("lossless", eps, 0.0, 0.0, 0.0).permittivity(3.5e9)
    theta = np.linspace(0, np.pi / 2, 9001)
    _, tm = fresnel_coefficients(np.cos(theta), lossless)
    assert np.rad2deg(theta[np.argmin(np.abs(tm))]) == pytest.approx(np.rad2deg(np.arctan(np.sqrt(eps))), abs=0.05)
    assert np.abs(tm).min() < 1e-3


def test_reflection_power_splits_vertical_polarisation_into_te_and_tm() -> None:
    eta = MATERIALS["concrete"].permittivity(3.5e9)
    k = np.array([np.cos(0.3), 0.0, -np.sin(0.3)])  # downwards onto the ground: pure TM
    assert reflection_power(k, np.array([0, 0, 1.0]), eta) == pytest.approx(abs(r_tm(np.pi / 2 - 0.3, eta)) ** 2)
    k = np.array([np.cos(0.4), np.sin(0.4), 0.0])  # horizontal onto a wall x = const: pure TE
    assert reflection_power(k, np.array([-1.0, 0, 0]), eta) == pytest.approx(abs(r_te(0.4, eta)) ** 2)
    k = np.array([1.0, 1.0, -1.0]) / np.sqrt(3)  # oblique: between the two
    p = reflection_power(k, np.array([-1.0, 0, 0]), eta)
    theta = np.arccos(1 / np.sqrt(3))
    lo, hi = sorted([abs(r_te(theta, eta)) ** 2, abs(r_tm(theta, eta)) ** 2])
    assert lo < p < hi


def test_segment_box_overlap() -> None:
    lo, hi = np.array([[1.0, -1, -1]]), np.array([[2.0, 1, 1]])
    p0 = np.array([[0.0, 0, 0], [0.0, 5, 0], [1.5, 0, 0]])
    p1 = np.array([[4.0, 0, 0], [4.0, 5, 0], [1.6, 0, 0]])
    t_in, t_out = segment_box_overlap(p0, p1, lo, hi)
    assert (t_in[0, 0], t_out[0, 0]) == pytest.approx((0.25, 0.5))
    assert t_out[1, 0] <= t_in[1, 0]  # misses
    assert (t_in[2, 0], t_out[2, 0]) == pytest.approx((0.0, 1.0))  # fully inside


def test_free_space_has_only_the_friis_los_path() -> None:
    city = ProceduralCity.from_scene("free_space")
    tx, rx = np.array([0.0, 0, 30]), np.array([[100.0, 0, 1.5], [0, -50, 1.5]])
    table = city.trace(tx, rx, 3.5e9, seed=0)
    assert list(table.dtypes.astype(str)) == list(PATH_COLUMNS.values())
    assert list(table["interactions"]) == ["LOS", "LOS"]
    d = np.linalg.norm(rx - tx, axis=1)
    np.testing.assert_allclose(table["power_lin"], friis(d, 3.5e9), rtol=1e-12)
    np.testing.assert_allclose(table["delay_s"], d / C, rtol=1e-12)
    np.testing.assert_allclose(table["aod_el_rad"], np.arcsin((rx[:, 2] - 30) / d), rtol=1e-12)
    np.testing.assert_allclose(table["aod_az_rad"], [0.0, -np.pi / 2], atol=1e-12)


def test_ground_reflection_is_the_two_ray_model() -> None:
    city = ProceduralCity.from_scene("ground")
    tx, rx, f = np.array([0.0, 0, 30]), np.array([[100.0, 0, 1.5]]), 2.1e9
    table = city.trace(tx, rx, f, seed=0)
    ground = table[table["interactions"] == "R"].iloc[0]
    length = np.hypot(100.0, 31.5)
    theta = np.arctan2(100.0, 31.5)  # from the normal
    expected = friis(length, f) * abs(r_tm(theta, eta_of("medium_dry_ground", f))) ** 2
    assert ground["power_lin"] == pytest.approx(expected, rel=1e-3)
    assert ground["delay_s"] == pytest.approx(length / C)
    assert ground["aod_el_rad"] == pytest.approx(-np.arctan2(31.5, 100.0))


def test_penetration_reduces_power_by_walls_and_interior_loss() -> None:
    box = (np.array([[40.0, -10, 0]]), np.array([[60.0, 10, 20]]))
    tx, rx = np.array([0.0, 0, 10]), np.array([[100.0, 0, 1.5]])
    d = np.linalg.norm(rx[0] - tx)
    for f in (2.1e9, 3.5e9):
        table = ProceduralCity.with_buildings(*box, ground_reflection=False).trace(tx, rx, f, seed=0)
        direct = table[table["interactions"] == "T"]
        assert len(direct) == 1
        loss_db = 2 * (5 + 4 * f / 1e9) + 0.5 * d * 20.0 / 100.0  # TR 38.901: concrete walls + 0.5 dB/m inside
        assert 10 * np.log10(friis(d, f) / direct["power_lin"].iloc[0]) == pytest.approx(loss_db, abs=1e-6)
    assert wall_loss_db(3.5e9) > wall_loss_db(2.1e9)
    blocked = ProceduralCity.with_buildings(*box, ground_reflection=False, penetration=False).trace(tx, rx, 3.5e9, 0)
    assert len(blocked) == 0


def test_first_order_wall_reflection_by_image_method() -> None:
    box = (np.array([[50.0, 20, 0]]), np.array([[80.0, 40, 30]]))
    city = ProceduralCity.with_buildings(*box, ground_reflection=False)
    tx, rx, f = np.array([0.0, 0, 10]), np.array([[120.0, 0, 10]]), 3.5e9
    table = city.trace(tx, rx, f, seed=0)
    assert sorted(table["interactions"]) == ["LOS", "R"]
    wall = table[table["interactions"] == "R"].iloc[0]
    length = np.hypot(120.0, 40.0)  # to the image (0, 40, 10)
    theta = np.arctan2(120.0, 40.0)
    assert wall["power_lin"] == pytest.approx(friis(length, f) * abs(r_te(theta, eta_of("concrete", f))) ** 2, rel=1e-3)
    assert wall["aod_az_rad"] == pytest.approx(np.arctan2(20.0, 60.0))  # towards the point (60, 20)
    assert wall["delay_s"] == pytest.approx(length / C)


def test_second_order_reflections_in_a_street_canyon() -> None:
    lo = np.array([[0.0, 10, 0], [0.0, -30, 0]])
    hi = np.array([[200.0, 30, 30], [200.0, -10, 30]])
    tx, rx, f = np.array([20.0, 0, 10]), np.array([[180.0, 0, 10]]), 3.5e9
    first = ProceduralCity.with_buildings(lo, hi, ground_reflection=False, max_reflections=1).trace(tx, rx, f, 0)
    second = ProceduralCity.with_buildings(lo, hi, ground_reflection=False, max_reflections=2).trace(tx, rx, f, 0)
    assert sorted(first["interactions"]) == ["LOS", "R", "R"]
    rr = second[second["interactions"] == "RR"]
    assert len(rr) == 2
    length = np.hypot(160.0, 40.0)
    gamma = abs(r_te(np.arctan2(160.0, 40.0), eta_of("concrete", f))) ** 2
    np.testing.assert_allclose(rr["power_lin"], friis(length, f) * gamma**2, rtol=1e-3)


def test_reflected_paths_must_be_unobstructed() -> None:
    # A blocker between the transmitter and the reflecting wall removes the wall reflection.
    lo = np.array([[50.0, 20, 0], [25.0, 5, 0]])
    hi = np.array([[80.0, 40, 30], [35.0, 15, 30]])
    city = ProceduralCity.with_buildings(lo, hi, ground_reflection=False)
    table = city.trace(np.array([0.0, 0, 10]), np.array([[120.0, 0, 10]]), 3.5e9, 0)
    assert "R" not in set(table["interactions"])


def test_trace_is_vectorised_and_fast_enough() -> None:
    city = ProceduralCity(seed=0)
    rng = np.random.default_rng(0)
    xy = rng.uniform(-190, 190, (3000, 2))
    xy = xy[city.is_outdoor(xy)][:1000]
    rx = np.column_stack([xy, np.full(len(xy), 1.5)])
    tx = city.rooftops()[0] + np.array([0, 0, 3.0])
    table = city.trace(tx, rx, 3.5e9, 0)
    assert table["rx_index"].nunique() == len(rx)  # direct path (LOS or through walls) always exists
    assert isinstance(table, pd.DataFrame) and (table["power_lin"] > 0).all()


def test_point_cloud_covers_ground_and_buildings() -> None:
    city = ProceduralCity(seed=2, size_m=200.0, num_buildings=5)
    xyz, cls = city.sample_point_cloud(0.2, 0.0, seed=1)
    xyz2, _ = city.sample_point_cloud(0.2, 0.0, seed=1)
    np.testing.assert_array_equal(xyz, xyz2)
    assert set(np.unique(cls)) == {2, 6}
    assert np.all(xyz[cls == 2, 2] == 0.0) and city.is_outdoor(xyz[cls == 2, :2]).all()
    assert xyz[cls == 6, 2].max() == pytest.approx(city.box_hi[:, 2].max(), abs=1e-9)


def test_bad_options_are_config_errors() -> None:
    with pytest.raises(ConfigError, match="max_reflections"):
        ProceduralCity(max_reflections=3)
    with pytest.raises(ConfigError, match="wall_material"):
        ProceduralCity(wall_material="cheese")
    with pytest.raises(ConfigError, match="valid: city"):
        ProceduralCity.from_scene("atlantis")
