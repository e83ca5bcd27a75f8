"""build_scenario on a tiny procedural city: layout, reproducibility, round-2 changes, truth files."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from rflscm.config import from_dict, load_config
from rflscm.data import load_scenario
from rflscm.errors import ConfigError
from rflscm.geometry import AngleGrid
from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario
from rflscm.sim.builder import choose_sites

TINY = SimulationConfig(
    name="tiny-sim",
    num_sites=2,
    max_grids=60,
    seed=11,
    site_radius_m=120.0,
    point_cloud_points_per_m2=0.05,
    angle_grid=AngleGrid(num_el=31, num_az=36, el_min_deg=-90.0, el_step_deg=6.0),
)


def city() -> ProceduralCity:
    return ProceduralCity(seed=2, size_m=260.0, num_buildings=14)


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("builder") / "a"
    stats: dict[str, float] = {}
    build_scenario(city(), TINY, out, progress=False, stats=stats)
    assert stats["num_grids"] == 60 and stats["paths_per_grid"] > 1
    return out


def test_layout_cells_grids_and_files(built: Path) -> None:
    sc = load_scenario(built)
    cells = sc.cells[1]
    assert len(cells) == 2 * 3 * 2  # sites × sectors × carriers
    assert set(cells["freq_hz"]) == {3.5e9, 2.1e9} and sc.meta.frequencies_hz[0] == 3.5e9
    for freq, group in cells.groupby("freq_hz"):
        np.testing.assert_allclose(group["spacing_h_m"], 0.5 * 299_792_458.0 / freq)  # array designed per carrier
    assert cells.groupby("site_id")[["x", "y", "z"]].nunique().max().max() == 1  # co-sited
    assert len(sc.grids) == 60 and city().is_outdoor(sc.grids[["x", "y"]].to_numpy()).all()
    np.testing.assert_allclose(sc.grids["z"], 1.5)
    np.testing.assert_allclose(np.mod(sc.grids[["x", "y"]].to_numpy() - 5.0, 10.0), 0.0, atol=1e-9)
    for name in ("paths.parquet", "aps.parquet", "rsrp_noiseless.parquet"):
        assert (built / "truth" / name).is_file()
    assert sc.meta.simulation["backend"] == "procedural" and sc.meta.simulation["seed"] == 11
    assert set(sc.meta.codebooks) >= {"ssb8", "csi32", "ssb8_b", "csi32_b"}
    assert sc.point_cloud is not None and sc.point_cloud.num_points > 100


def test_sites_sit_on_roof_edges_above_the_roof() -> None:
    backend = city()
    sites = choose_sites(backend, TINY, np.random.default_rng(0))
    roofs = backend.rooftops()
    assert len(sites) == 2 and len(np.unique(sites[:, :2], axis=0)) == 2
    assert not backend.is_outdoor(sites[:, :2]).any()  # still on a roof
    roof_z = roofs[np.argmin(np.linalg.norm(roofs[None, :, :2] - sites[:, None, :2], axis=2), axis=1), 2]
    np.testing.assert_allclose(sites[:, 2], roof_z + 3.0)
    centre_sites = choose_sites(backend, dataclasses.replace(TINY, site_placement="center"), np.random.default_rng(0))
    assert np.all(np.linalg.norm(centre_sites[:, :2], axis=1) >= np.linalg.norm(sites[:, :2], axis=1) - 1e-9)


def test_measurements_are_quantised_thresholded_and_per_detected_pair(built: Path) -> None:
    m = load_scenario(built).measurements
    values = m["rsrp_dbm"].dropna()
    assert (values == np.round(values)).all() and values.min() >= -120.0 and values.max() <= -31.0
    assert m["rsrp_dbm"].isna().any()
    ssb = m[m["beam_type"] == "ssb"]
    detected = ssb.groupby(["round", "cell_id", "grid_id"])["rsrp_dbm"].apply(lambda s: s.notna().any())
    assert detected.all()  # every listed pair has a reported SSB beam
    beams = m.groupby(["round", "cell_id", "grid_id", "beam_type"]).size().unstack()
    assert set(beams["ssb"]) == {8} and set(beams["csi"]) == {32}  # every beam of a detected pair is listed


def test_same_seed_gives_identical_files_and_another_seed_differs(built: Path, tmp_path: Path) -> None:
    build_scenario(city(), TINY, tmp_path / "b", progress=False)
    files = sorted(p.relative_to(built) for p in built.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(tmp_path / "b") for p in (tmp_path / "b").rglob("*") if p.is_file())
    for name in files:
        assert (built / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name
    build_scenario(city(), dataclasses.replace(TINY, seed=12), tmp_path / "c", progress=False)
    assert (built / "measurements.parquet").read_bytes() != (tmp_path / "c" / "measurements.parquet").read_bytes()


def test_round2_changes_only_the_chosen_cells(built: Path) -> None:
    sc = load_scenario(built)
    changes = {c["cell_id"]: c for c in sc.meta.simulation["round2_changes"]}
    assert len(changes) == 4 and {c["method"] for c in changes.values()} <= {"a", "b"}  # 1/3 of 6 per carrier
    r1, r2 = sc.cells[1].set_index("cell_id"), sc.cells[2].set_index("cell_id")
    for cell in sc.cell_ids():
        same = r1.loc[cell].equals(r2.loc[cell])
        assert same == (cell not in changes)
    truth = pd.read_parquet(built / "truth" / "rsrp_noiseless.parquet")
    wide = truth.pivot_table(index=["cell_id", "grid_id", "beam_type", "beam_id"], columns="round", values="rsrp_dbm")
    unchanged = ~wide.index.get_level_values("cell_id").isin(list(changes))
    np.testing.assert_array_equal(wide.loc[unchanged, 1].to_numpy(), wide.loc[unchanged, 2].to_numpy())
    for cell, change in changes.items():
        rows = wide.xs(cell, level="cell_id")
        diff = (rows[1] - rows[2]).abs().replace(np.inf, np.nan)
        assert diff.max() > 1.0, change  # every changed cell really changes its RSRP


def test_co_sited_cells_share_the_true_aps(built: Path) -> None:
    sc = load_scenario(built)
    aps = pd.read_parquet(built / "truth" / "aps.parquet")
    assert aps["bin"].max() < TINY.angle_grid.num_bins and (aps["power_lin"] > 0).all()
    cells = sc.cells[1]
    for _, group in cells.groupby(["site_id", "freq_hz"]):
        first, *others = group["cell_id"].tolist()
        ref = aps[aps["cell_id"] == first].drop(columns="cell_id").reset_index(drop=True)
        for other in others:
            same = aps[aps["cell_id"] == other].drop(columns="cell_id").reset_index(drop=True)
            pd.testing.assert_frame_equal(same, ref)
    site1 = cells[cells["site_id"] == 1]
    a35 = aps[aps["cell_id"] == site1.loc[site1["freq_hz"] == 3.5e9, "cell_id"].iloc[0]]["power_lin"].sum()
    a21 = aps[aps["cell_id"] == site1.loc[site1["freq_hz"] == 2.1e9, "cell_id"].iloc[0]]["power_lin"].sum()
    assert a21 > a35  # lower carrier: less path loss (λ²) and less penetration loss


def test_explicit_sites_and_a_free_space_scene(tmp_path: Path) -> None:
    config = dataclasses.replace(TINY, sites=((0.0, 0.0, 25.0),), carriers_hz=(3.5e9,), max_grids=20)
    build_scenario(ProceduralCity.from_scene("free_space", size_m=200.0), config, tmp_path / "s", progress=False)
    sc = load_scenario(tmp_path / "s")
    np.testing.assert_allclose(sc.cells[1][["x", "y", "z"]].drop_duplicates().to_numpy(), [[0.0, 0.0, 25.0]])
    paths = pd.read_parquet(tmp_path / "s" / "truth" / "paths.parquet")
    assert set(paths["interactions"]) == {"LOS"} and len(paths) == 20 * 4


def test_out_dir_must_be_empty(built: Path) -> None:
    with pytest.raises(ConfigError, match="not empty"):
        build_scenario(city(), TINY, built, progress=False)


def test_backend_options_are_checked() -> None:
    from rflscm.sim import make_backend

    with pytest.raises(ConfigError, match="valid keys: size_m"):
        make_backend("procedural", "city", options={"num_building": 3})
    with pytest.raises(ConfigError, match="valid: procedural, sionna"):
        make_backend("blender")
    assert make_backend("procedural", "small", seed=1, options={"num_buildings": 3}).num_buildings == 3


def test_config_yaml_is_strict_and_checks_units(tmp_path: Path) -> None:
    path = tmp_path / "sim.yaml"
    path.write_text("num_sites: 3\nangle_grid: {num_el: 19, num_az: 24, el_min_deg: -90, el_step_deg: 10}\n")
    config = load_config(SimulationConfig, path)
    assert config.num_sites == 3 and config.angle_grid.num_bins == 19 * 24
    with pytest.raises(ConfigError, match="unknown key"):
        from_dict(SimulationConfig, {"num_site": 3})
    with pytest.raises(ConfigError, match="looks like MHz or GHz"):
        SimulationConfig(carriers_hz=(3500.0,))
    with pytest.raises(ConfigError, match="round2_change_fraction"):
        SimulationConfig(round2_change_fraction=1.5)
