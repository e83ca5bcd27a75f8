"""The field regime streamed cell by cell (rflscm.sim.field_stream) writes what the whole-table path wrote:
field_rsrp → report → write_truth and the samples' truth on long tables, the same rows, order and values, under
every reporting rule (SS-SINR or threshold, top-N, serving-cell CSI-RS, drive routes) and channel effect."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from rflscm.data import load_scenario
from rflscm.geometry import AngleGrid
from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario
from rflscm.sim.field import FieldConfig, field_rsrp, report
from rflscm.sim.field_stream import _keep_top, stream_field
from rflscm.sim.paths import PATHS_FILE, true_aps_table, write_truth
from rflscm.sim.stream import MemoryPaths, SpilledPaths

TINY = SimulationConfig(
    name="tiny-field-stream",
    num_sites=3,
    max_grids=45,
    seed=8,
    site_radius_m=120.0,
    point_cloud_points_per_m2=0.05,
    angle_grid=AngleGrid(num_el=31, num_az=36, el_min_deg=-90.0, el_step_deg=6.0),
)


@pytest.fixture(scope="module")
def traced(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("field_stream") / "ideal"
    build_scenario(ProceduralCity(seed=4, size_m=260.0, num_buildings=14), TINY, out, progress=False)
    return out


def _sample_truth(folder: Path, scenario, paths: pd.DataFrame, samples: pd.DataFrame, k: int, grid: AngleGrid) -> None:
    """The whole-table samples' truth as `write_measurements` wrote it before streaming."""
    samples.astype({"round": "int8", "grid_id": "int32", "point_id": "int16", "weight": "float32"}).to_parquet(
        folder / "samples.parquet", index=False
    )
    frames = []
    for rnd, sub in samples.groupby("round"):
        weight = pd.Series(sub["weight"].to_numpy(), index=pd.MultiIndex.from_frame(sub[["grid_id", "point_id"]]))
        w = weight.reindex(pd.MultiIndex.from_frame(paths[["grid_id", "point_id"]].astype("int64"))).fillna(0.0)
        weighted = paths.assign(power_lin=paths["power_lin"].to_numpy() * w.to_numpy() * k)
        aps = true_aps_table(weighted[weighted["power_lin"] > 0], scenario.cells[1], grid, k)
        frames.append(aps.assign(round=np.int8(rnd)))
    table = pd.concat(frames, ignore_index=True)[["round", "cell_id", "grid_id", "bin", "power_lin"]]
    table.astype({"power_lin": "float32"}).to_parquet(folder / "aps_samples.parquet", index=False)


RULES = {
    "defaults": {},
    "top-n, every cell's CSI-RS, drive routes": {
        "ssb_top_n": 3,
        "csi_serving_only": False,
        "csi_top_n": 2,
        "drive_routes": 2,
        "drive_route_grids": 10,
    },
    "threshold detection, no fading, no array error": {
        "ssb_detection": "threshold",
        "fading": False,
        "array_amp_sigma_db": 0.0,
        "array_phase_sigma_deg": 0.0,
        "ssb_top_n": 2,
    },
    "every effect off": dataclasses.asdict(FieldConfig.ideal()),
    "loud interference": {"ssb_sinr_db": 3.0, "samples_per_grid": 7, "csi_top_n": None},
}


@pytest.mark.parametrize("rule", list(RULES))
def test_streamed_field_regime_equals_the_whole_table_path(traced: Path, tmp_path: Path, rule: str) -> None:
    sc = load_scenario(traced)
    paths = pd.read_parquet(traced / "truth" / PATHS_FILE)
    paths = paths.astype({"power_lin": "float64", "aod_el_rad": "float64", "aod_az_rad": "float64"})
    paths["interactions"] = paths["interactions"].astype(str)
    cfg = FieldConfig(**RULES[rule])
    k, floor = TINY.points_per_grid, -130.0

    ref = tmp_path / "ref"
    true_rsrp, expected, samples = field_rsrp(sc, paths, k, cfg, np.random.default_rng(3))
    want = report(true_rsrp, sc, cfg, np.random.default_rng(9))
    write_truth(ref, sc, paths, expected, pd.Series(k, index=sc.grid_ids()), TINY.angle_grid, floor)
    _sample_truth(ref, sc, paths, samples, k, TINY.angle_grid)

    store = SpilledPaths(tmp_path / "spill")
    for key, group in MemoryPaths(paths)._groups.items():
        store.add(*key, group)
    got_dir = tmp_path / "got"
    rng = np.random.default_rng(9)
    stream_field(sc, store, k, cfg, np.random.default_rng(3), rng, got_dir, floor, TINY.angle_grid, tmp_path / "m.pq")
    got = pd.read_parquet(tmp_path / "m.pq")

    assert len(want) > 100 and want["rsrp_dbm"].notna().sum() > 50
    if rule == "defaults":  # SS-SINR detection and the serving cell's CSI-RS really removed rows here
        assert (want["beam_type"] == "csi").sum() < (want["beam_type"] == "ssb").sum() * 4
    if RULES[rule].get("drive_routes"):  # only the grids along the routes are reported
        assert want["grid_id"].nunique() < len(sc.grids)
    pd.testing.assert_frame_equal(
        got.reset_index(drop=True), want.astype({"beam_type": got["beam_type"].dtype}), check_exact=True
    )
    for name in ("aps.parquet", "rsrp_noiseless.parquet", "samples.parquet", "aps_samples.parquet"):
        pd.testing.assert_frame_equal(pd.read_parquet(got_dir / name), pd.read_parquet(ref / name), check_exact=True)


def test_keep_top_keeps_the_strongest_and_breaks_ties_by_the_lower_beam() -> None:
    values = np.array([[1.0, 3.0, 3.0, np.nan, 2.0], [np.nan, np.nan, -1.0, np.nan, np.nan]])
    got = _keep_top(values, 2)
    np.testing.assert_array_equal(np.isnan(got), [[True, False, False, True, True], [True, True, False, True, True]])
    assert got[0, 1] == 3.0 and got[0, 2] == 3.0
    ties = _keep_top(np.array([[5.0, 5.0, 5.0]]), 2)
    np.testing.assert_array_equal(np.isnan(ties), [[False, False, True]])


def test_the_interference_sum_is_the_same_in_blocks(monkeypatch: pytest.MonkeyPatch) -> None:
    import rflscm.sim.field_stream as fs

    rng = np.random.default_rng(0)
    stack = 10.0 ** rng.uniform(-14, -6, (6, 7, 8))  # [cells, grids, beams] mW: sums where rounding matters
    stack[rng.random(stack.shape) < 0.3] = 0.0
    whole = fs._sum_in_table_order(stack)
    monkeypatch.setattr(fs, "_SUM_COLUMNS", 5)  # 56 groups in 12 blocks, the last one short
    blocks = fs._sum_in_table_order(stack)
    assert np.array_equal(blocks, whole)
    np.testing.assert_allclose(whole, stack.sum(axis=0), rtol=1e-12)
