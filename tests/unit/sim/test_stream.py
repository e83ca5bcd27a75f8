"""The streamed simulation (per (site, carrier) paths, per (round, cell) RSRP) writes what the whole-table
path wrote: noiseless_rsrp → measure → write_truth on one table, same rows, order and values."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from rflscm.data import load_scenario
from rflscm.geometry import AngleGrid
from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario
from rflscm.sim.builder import make_cells, make_round2, trace_all
from rflscm.sim.noise import measure
from rflscm.sim.paths import APS_FILE, PATHS_FILE, RSRP_FILE, noiseless_rsrp, write_truth
from rflscm.sim.stream import MemoryPaths, ParquetAppender, SpilledPaths, compact_paths, stream_ideal

TINY = SimulationConfig(
    name="tiny-stream",
    num_sites=3,
    carriers_hz=(3.5e9, 2.1e9),
    max_grids=50,
    seed=5,
    site_radius_m=120.0,
    point_cloud_points_per_m2=0.05,
    angle_grid=AngleGrid(num_el=31, num_az=36, el_min_deg=-90.0, el_step_deg=6.0),
)


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("stream") / "a"
    build_scenario(ProceduralCity(seed=2, size_m=260.0, num_buildings=14), TINY, out, progress=False)
    return out


def _reference(scenario, paths: pd.DataFrame, config: SimulationConfig, rng, folder: Path) -> pd.DataFrame:
    """The whole-table path of the ideal regime as it was before streaming."""
    counts = pd.Series(config.points_per_grid, index=scenario.grid_ids())
    noiseless = noiseless_rsrp(scenario, paths, counts)
    measurements = measure(noiseless, config.measurement_model, rng, detect_on="ssb")
    floor = config.threshold_dbm - config.truth_rsrp_margin_db
    write_truth(folder, scenario, paths, noiseless, counts, config.angle_grid, floor)
    return measurements


@pytest.mark.parametrize("spilled", [False, True])
def test_stream_ideal_equals_the_whole_table_path(built: Path, tmp_path: Path, spilled: bool) -> None:
    sc = load_scenario(built)
    paths = pd.read_parquet(built / "truth" / PATHS_FILE)
    paths = paths.astype({"power_lin": "float64", "aod_el_rad": "float64", "aod_az_rad": "float64"})
    seed = 123
    expected = _reference(sc, paths, TINY, np.random.default_rng(seed), tmp_path / "ref")
    if spilled:
        store = SpilledPaths(tmp_path / "spill")
        for key, group in MemoryPaths(paths)._groups.items():
            store.add(*key, group)
    else:
        store = MemoryPaths(paths)
    floor = TINY.threshold_dbm - TINY.truth_rsrp_margin_db
    got = stream_ideal(
        sc, store, TINY.points_per_grid, TINY.measurement_model, np.random.default_rng(seed), "ssb",
        tmp_path / "new", floor, TINY.angle_grid,
    )  # fmt: skip
    pd.testing.assert_frame_equal(got, expected.reset_index(drop=True), check_exact=True)
    assert got["rsrp_dbm"].notna().any() and got["rsrp_dbm"].isna().any()  # both reported and missing beams
    for name in (APS_FILE, RSRP_FILE):
        a, b = pd.read_parquet(tmp_path / "ref" / name), pd.read_parquet(tmp_path / "new" / name)
        assert len(a) > 0
        pd.testing.assert_frame_equal(b, a, check_exact=True)
    if spilled:
        store.remove()
        assert not (tmp_path / "spill").exists()
        return
    # the same measurements appended to a file block by block (what build_scenario does)
    file = tmp_path / "m.parquet"
    empty = stream_ideal(
        sc, store, TINY.points_per_grid, TINY.measurement_model, np.random.default_rng(seed), "ssb",
        tmp_path / "again", floor, TINY.angle_grid, measurements_file=file,
    )  # fmt: skip
    assert len(empty) == 0
    pd.testing.assert_frame_equal(pd.read_parquet(file), expected.reset_index(drop=True), check_exact=True)
    import pyarrow.parquet as pq

    assert pq.ParquetFile(file).metadata.num_rows == len(expected)


def test_build_streams_the_trace_and_writes_every_path(built: Path) -> None:
    """The trace sink saw every path: truth/paths.parquet equals the whole trace, and no spill is left."""
    backend = ProceduralCity(seed=2, size_m=260.0, num_buildings=14)
    sc = load_scenario(built)
    rng = np.random.default_rng(TINY.seed)
    from rflscm.sim.builder import area_center, choose_sites, receiver_points

    scan_rng_free = backend.sample_point_cloud(TINY.point_cloud_points_per_m2, TINY.point_cloud_noise_m, TINY.seed)
    from rflscm.data import PointCloud

    sites = choose_sites(backend, TINY, rng, PointCloud(*scan_rng_free))
    cells = make_cells(sites, TINY, rng)
    make_round2(cells, TINY, rng)
    rx = receiver_points(backend, sc.grids, TINY, rng)
    whole, _ = trace_all(backend, sites, rx, sc.grid_ids(), TINY, progress=False)
    seen: list[tuple[int, float]] = []
    _, stats = trace_all(backend, sites, rx, sc.grid_ids(), TINY, False, sink=lambda s, f, t: seen.append((s, f)))
    assert seen == [(s, f) for s in (1, 2, 3) for f in TINY.carriers_hz]
    assert stats["paths_per_grid"] > 1 and area_center(backend, TINY).shape == (2,)
    written = pd.read_parquet(built / "truth" / PATHS_FILE)
    compact_paths(whole).to_parquet(built.parent / "whole.parquet", index=False)  # as the whole-table path wrote it
    pd.testing.assert_frame_equal(written, pd.read_parquet(built.parent / "whole.parquet"), check_exact=True)
    assert not (built / ".trace").exists()


def test_appender_writes_row_groups_and_an_empty_file(tmp_path: Path) -> None:
    import pyarrow.parquet as pq

    empty = pd.DataFrame({"a": pd.Series(dtype="int32"), "t": pd.Categorical([], categories=["x", "y"])})
    with ParquetAppender(tmp_path / "e.parquet", empty) as out:
        out.append(empty)
    assert len(pd.read_parquet(tmp_path / "e.parquet")) == 0
    with ParquetAppender(tmp_path / "f.parquet", empty, rows_per_group=3) as out:
        for i in range(5):
            labels = ["x", "y"] if i % 2 == 0 else ["y", "y"]  # categories differ between frames
            out.append(pd.DataFrame({"a": np.full(2, i, dtype=np.int32), "t": pd.Categorical(labels)}))
    back = pd.read_parquet(tmp_path / "f.parquet")
    assert back["a"].tolist() == [0, 0, 1, 1, 2, 2, 3, 3, 4, 4]
    assert back["t"].astype(str).tolist() == ["x", "y", "y", "y", "x", "y", "y", "y", "x", "y"]
    assert pq.ParquetFile(tmp_path / "f.parquet").num_row_groups == 3  # flushed at >= 3 rows: 4 + 4 + 2


def test_a_scenario_with_any_detection_streams_too(tmp_path: Path) -> None:
    config = dataclasses.replace(TINY, detect_on="any", num_sites=1, max_grids=20, truth_rsrp_margin_db=None)
    out = build_scenario(ProceduralCity(seed=2, size_m=260.0, num_buildings=14), config, tmp_path / "b", progress=False)
    sc = load_scenario(out)
    truth = pd.read_parquet(out / "truth" / RSRP_FILE)
    assert len(truth) == 2 * len(sc.cell_ids()) * len(sc.grid_ids()) * 40  # no floor: every row
    assert len(sc.measurements) > 0


def test_a_trace_range_drops_only_the_far_receivers(built: Path, tmp_path: Path) -> None:
    """With ``trace_range_m`` a site's paths are those of the full trace at the receivers within range: same
    rows, same values; a range beyond every receiver changes nothing."""
    backend = ProceduralCity(seed=2, size_m=260.0, num_buildings=14)
    sc = load_scenario(built)
    sites = sc.cells[1].drop_duplicates("site_id")[["x", "y", "z"]].to_numpy()
    rng = np.random.default_rng(0)
    rx = np.column_stack([rng.uniform(-120, 120, (200, 2)), np.full(200, 1.5)])
    rx = rx[backend.is_outdoor(rx[:, :2])]
    grid_ids = np.arange(len(rx)) // TINY.points_per_grid
    config = dataclasses.replace(TINY, points_per_grid=1)
    whole, _ = trace_all(backend, sites, rx, np.arange(len(rx)), config, progress=False)
    near, _ = trace_all(
        backend, sites, rx, np.arange(len(rx)), dataclasses.replace(config, trace_range_m=80.0), progress=False
    )
    far = np.hypot(
        rx[whole["grid_id"].to_numpy(), 0] - sites[whole["site_id"].to_numpy() - 1, 0],
        rx[whole["grid_id"].to_numpy(), 1] - sites[whole["site_id"].to_numpy() - 1, 1],
    )
    assert 0 < len(near) < len(whole) and len(grid_ids) == len(rx)
    expected = whole[far <= 80.0].reset_index(drop=True)
    pd.testing.assert_frame_equal(near.reset_index(drop=True), expected, check_exact=True)
    every, _ = trace_all(
        backend, sites, rx, np.arange(len(rx)), dataclasses.replace(config, trace_range_m=1e4), progress=False
    )
    pd.testing.assert_frame_equal(every, whole, check_exact=True)
    empty, _ = trace_all(backend, sites + 1e5, rx, np.arange(len(rx)), dataclasses.replace(config, trace_range_m=1.0))
    assert len(empty) == 0
    with pytest.raises(Exception, match="trace_range_m"):
        dataclasses.replace(config, trace_range_m=0.0)


def test_a_grown_city_gets_a_trace_range_and_the_default_one_none() -> None:
    from rflscm.sim.builder import GROWN_TRACE_RANGE_M, grow_procedural

    assert grow_procedural(SimulationConfig(), "city").trace_range_m is None  # default city: every receiver
    grown = grow_procedural(SimulationConfig(num_sites=19), "city")
    assert grown.trace_range_m == GROWN_TRACE_RANGE_M
    assert grow_procedural(SimulationConfig(num_sites=19, trace_range_m=300.0), "city").trace_range_m == 300.0
