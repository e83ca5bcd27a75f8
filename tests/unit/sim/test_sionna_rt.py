"""Sionna RT backend: geometry helpers (numpy only) and real traces (needs the `rt` extra)."""

from __future__ import annotations

import importlib.util

import numpy as np
import pandas as pd
import pytest

from rflscm.errors import ConfigError
from rflscm.sim.backend import PATH_COLUMNS, SceneBackend
from rflscm.sim.sionna_rt import (
    ASPRS_BUILDING,
    ASPRS_GROUND,
    SionnaSceneBackend,
    _interaction_strings,
    _rasterize_max_z,
    available_scenes,
)

SPEED_OF_LIGHT = 299_792_458.0
# The module sets the Mitsuba variant and DRJIT_LIBLLVM_PATH before Sionna is
# imported, so the check must not import `sionna.rt` itself.
needs_rt = pytest.mark.skipif(
    importlib.util.find_spec("sionna") is None,
    reason="Sionna RT extra not installed (pip install -e .[rt]; apt-get install -y libllvm19)",
)


def test_rasterize_max_z_interpolates_plane_and_keeps_highest_surface() -> None:
    # A sloped triangle z = 0.1 x over a flat one at z = 2: the cell keeps the higher.
    sloped = [[0, 0, 0], [10, 0, 1], [0, 10, 0]]
    flat = [[0, 0, 2], [4, 0, 2], [0, 4, 2]]
    wall = [[0, 0, 0], [10, 0, 0], [10, 0, 50]]  # vertical: no footprint
    tri = np.array([sloped, flat, wall], dtype=float)
    z = _rasterize_max_z(tri, origin=np.array([0.5, 0.5]), cell_m=1.0, shape=(12, 12))
    assert z[0, 0] == pytest.approx(2.0)  # centre (0.5, 0.5): under both, flat is higher
    assert z[1, 6] == pytest.approx(0.65)  # centre (6.5, 1.5): sloped only
    assert np.isnan(z[9, 9])  # centre (9.5, 9.5): outside both (x + y > 10)
    assert np.nanmax(z) < 50  # the wall left no trace


def test_interaction_strings_map_sionna_codes_in_order() -> None:
    codes = np.array([[0, 0], [1, 0], [8, 1], [1, 8], [1, 1], [4, 2]], dtype=np.uint32)
    assert list(_interaction_strings(codes)) == ["LOS", "R", "DR", "RD", "RR", "TS"]


def test_unknown_scene_lists_valid_names() -> None:
    if importlib.util.find_spec("sionna") is None:
        with pytest.raises(ConfigError, match="pip install"):
            available_scenes()
        return
    assert {"munich", "etoile", "florence", "simple_street_canyon"} <= set(available_scenes())
    with pytest.raises(ConfigError, match="munich"):
        SionnaSceneBackend("atlantis")


@pytest.fixture(scope="module")
def canyon() -> SionnaSceneBackend:
    # Six buildings along a street at y ~ 0, floor at z ~ -0.03 m.
    return SionnaSceneBackend("simple_street_canyon", samples_per_src=100_000, rx_batch_size=2, deterministic=True)


@needs_rt
def test_los_paths_match_friis_and_point_at_receivers(canyon: SionnaSceneBackend) -> None:
    assert isinstance(canyon, SceneBackend)
    tx = np.array([-20.0, 0.0, 10.0])
    rx = np.array([[20.0, 0.0, 1.5], [0.0, 4.0, 1.5], [35.0, -3.0, 1.5]])
    freq_hz = 3.5e9
    done = []
    table = canyon.trace(tx, rx, freq_hz, seed=1, progress=lambda k, n: done.append((k, n)))
    assert done == [(2, 3), (3, 3)]  # two batches of at most 2 receivers
    assert list(table.columns) == list(PATH_COLUMNS)
    assert all(table[c].dtype == pd.api.types.pandas_dtype(t) for c, t in PATH_COLUMNS.items())
    assert not table.isna().any().any()
    assert (table["power_lin"] > 0).all() and set(table["rx_index"]) == {0, 1, 2}
    assert set("".join(table["interactions"].str.replace("LOS", ""))) <= set("RD")
    assert {"R", "RR", "D"} <= set(table["interactions"])
    los = table[table["interactions"] == "LOS"].set_index("rx_index").sort_index()
    assert list(los.index) == [0, 1, 2]
    vec = rx - tx
    dist = np.linalg.norm(vec, axis=1)
    friis = (SPEED_OF_LIGHT / freq_hz / (4 * np.pi * dist)) ** 2  # Friis, isotropic
    np.testing.assert_allclose(10 * np.log10(los["power_lin"] / friis), 0.0, atol=0.5)
    np.testing.assert_allclose(los["delay_s"], dist / SPEED_OF_LIGHT, rtol=1e-4)
    el = np.arcsin(vec[:, 2] / dist)
    az = np.arctan2(vec[:, 1], vec[:, 0])
    np.testing.assert_allclose(los["aod_el_rad"], el, atol=np.radians(1))
    az_err = np.angle(np.exp(1j * (los["aod_az_rad"] - az)))  # wrapped to (-pi, pi]
    np.testing.assert_allclose(az_err, 0, atol=np.radians(1))
    # The direct path is the first to arrive, and the table is sorted by delay.
    first = table.groupby("rx_index")["interactions"].first()
    assert list(first) == ["LOS"] * 3
    # Deterministic solver: the same seed gives the same table.
    pd.testing.assert_frame_equal(canyon.trace(tx, rx, freq_hz, seed=1), table)


@needs_rt
def test_geometry_roofs_indoor_and_ground(canyon: SionnaSceneBackend) -> None:
    roofs = canyon.rooftops()
    assert roofs.shape[1] == 3 and len(roofs) >= 3
    assert not canyon.is_outdoor(roofs[:, :2]).any()
    ground = canyon.ground_height(roofs[:, :2])
    assert (roofs[:, 2] > ground + 10).all()  # canyon buildings are 20-50 m tall
    street = np.array([[0.0, 0.0], [-50.0, 2.0], [500.0, 500.0]])
    assert canyon.is_outdoor(street).all()
    np.testing.assert_allclose(canyon.ground_height(street), -0.0308, atol=1e-3)
    lo, hi = canyon.bounds()
    assert (lo < hi).all() and hi[2] > 40


@needs_rt
def test_point_cloud_classes_density_and_noise(canyon: SionnaSceneBackend) -> None:
    xyz, cls = canyon.sample_point_cloud(points_per_m2=0.5, noise_std_m=0.0, seed=0)
    assert xyz.dtype == np.float64 and cls.dtype == np.uint8 and xyz.shape == (len(cls), 3)
    assert set(np.unique(cls)) == {ASPRS_GROUND, ASPRS_BUILDING}
    on_ground = cls == ASPRS_GROUND
    # Noise-free ground points lie on the floor and outside buildings.
    floor_z = canyon.ground_height(xyz[on_ground, :2])
    np.testing.assert_allclose(xyz[on_ground, 2], floor_z, atol=1e-3)
    assert canyon.is_outdoor(xyz[on_ground, :2]).all()
    dense, _ = canyon.sample_point_cloud(points_per_m2=2.0, noise_std_m=0.0, seed=0)
    assert len(dense) / len(xyz) == pytest.approx(4.0, rel=0.05)
    noisy, cls_n = canyon.sample_point_cloud(points_per_m2=0.5, noise_std_m=0.1, seed=0)
    noisy_ground = noisy[cls_n == ASPRS_GROUND]
    floor_err = noisy_ground[:, 2] - canyon.ground_height(noisy_ground[:, :2])
    assert np.std(floor_err) == pytest.approx(0.1, rel=0.1)
