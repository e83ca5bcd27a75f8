"""The field measurement model (issue 12): ideal equivalence, reporting rules, serving-cell CSI-RS,
array errors and fading, on a tiny procedural city and on hand-made toys."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from rflscm.antenna import CellAntenna, DFTCodebook, sensing_matrix
from rflscm.data import load_scenario
from rflscm.data.reporting import check_reporting, missing_bounds
from rflscm.geometry import AngleGrid
from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario
from rflscm.sim.field import FieldConfig, SampleSums, array_errors, field_rsrp, report
from rflscm.sim.noise import measure
from rflscm.sim.paths import noiseless_rsrp
from rflscm.sim.remeasure import remeasure

TINY = SimulationConfig(
    name="tiny-field",
    num_sites=2,
    max_grids=40,
    seed=5,
    site_radius_m=120.0,
    point_cloud_points_per_m2=0.05,
    angle_grid=AngleGrid(num_el=31, num_az=36, el_min_deg=-90.0, el_step_deg=6.0),
)


@pytest.fixture(scope="module")
def traced(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("field") / "ideal"
    build_scenario(ProceduralCity(seed=2, size_m=260.0, num_buildings=14), TINY, out, progress=False)
    return out


def _paths(folder: Path) -> pd.DataFrame:
    paths = pd.read_parquet(folder / "truth" / "paths.parquet")
    return paths.astype({"power_lin": "float64", "aod_el_rad": "float64", "aod_az_rad": "float64"})


def test_every_effect_off_reproduces_the_ideal_rsrp_exactly(traced: Path) -> None:
    sc = load_scenario(traced)
    paths = _paths(traced)
    ideal = FieldConfig.ideal()
    true_rsrp, expected, _ = field_rsrp(sc, paths, TINY.points_per_grid, ideal, np.random.default_rng(1))
    reference = noiseless_rsrp(sc, paths, TINY.points_per_grid)
    pd.testing.assert_frame_equal(true_rsrp, reference)
    pd.testing.assert_frame_equal(expected, reference)
    got = report(true_rsrp, sc, ideal, np.random.default_rng(7))
    want = measure(reference, TINY.measurement_model, np.random.default_rng(7), detect_on="ssb")
    pd.testing.assert_frame_equal(got, want)


def test_remeasured_field_scenario_declares_and_follows_its_rule(traced: Path, tmp_path: Path) -> None:
    cfg = dataclasses.replace(TINY, measurements="field", name="tiny-field-f")
    sc = load_scenario(remeasure(traced, cfg, tmp_path / "f"))
    assert sc.meta.reporting["ssb"].rule == "sinr" and sc.meta.reporting["csi"].top_n == 4
    assert sc.meta.simulation["measurements"] == "field" and sc.meta.simulation["field"]["samples_per_grid"] == 36
    assert check_reporting(sc) == []
    m = sc.measurements
    csi = m[m["beam_type"] == "csi"]
    freq = sc.cells[1].set_index("cell_id")["freq_hz"]
    # CSI-RS rows only for the serving cell: one cell per (round, grid, carrier), the strongest SSB cell
    per = csi[["round", "grid_id", "cell_id"]].drop_duplicates().assign(f=lambda d: freq.loc[d["cell_id"]].to_numpy())
    assert per.groupby(["round", "grid_id", "f"]).size().max() == 1
    ssb = m[m["beam_type"] == "ssb"].assign(f=lambda d: freq.loc[d["cell_id"]].to_numpy())
    best = ssb.groupby(["round", "grid_id", "f", "cell_id"])["rsrp_dbm"].max().reset_index()
    for row in per.itertuples():
        group = best[(best["round"] == row.round) & (best["grid_id"] == row.grid_id) & (best["f"] == row.f)]
        assert group["rsrp_dbm"].max() == group.loc[group["cell_id"] == row.cell_id, "rsrp_dbm"].iloc[0]
    assert (csi["rsrp_dbm"].notna().groupby([csi["round"], csi["cell_id"], csi["grid_id"]]).sum() <= 4).all()
    for name in ("samples.parquet", "aps_samples.parquet"):
        assert (sc.root / "truth" / name).is_file()
    samples = pd.read_parquet(sc.root / "truth" / "samples.parquet")
    one, two = (samples[samples["round"] == r].set_index(["grid_id", "point_id"])["weight"] for r in (1, 2))
    assert not one.reindex(two.index).fillna(0).equals(two)  # the rounds draw different samples


def _toy_scenario(rsrp: dict[tuple[int, int], list[float]], reporting: dict, freq: dict[int, float] | None = None):
    """A stand-in with the accessors report()/missing_bounds() use: cells 1, 2 (same carrier), 3 beams."""
    from rflscm.data.reporting import reporting_from_dict

    freq = freq or {1: 3.5e9, 2: 3.5e9}
    cells = pd.DataFrame({"cell_id": list(freq), "freq_hz": list(freq.values())})
    rows = [
        {"round": 1, "cell_id": c, "grid_id": g, "beam_type": t, "beam_id": b, "rsrp_dbm": v}
        for (c, g), values in rsrp.items()
        for t in ("ssb", "csi")
        for b, v in enumerate(values)
    ]
    meta = type("Meta", (), {"rsrp_threshold_dbm": -120.0, "reporting": reporting_from_dict(reporting)})()

    class Toy:
        pass

    toy = Toy()
    toy.meta, toy.cells, toy.measurements = meta, {1: cells}, pd.DataFrame(rows)
    toy.num_beams = lambda cell, beam_type, round=1: 3

    def rsrp_table(round, beam_type):
        sub = toy.measurements[(toy.measurements["round"] == round) & (toy.measurements["beam_type"] == beam_type)]
        wide = sub.pivot_table(index=["cell_id", "grid_id"], columns="beam_id", values="rsrp_dbm", dropna=False)
        wide = wide.reindex(columns=range(3))
        return wide.index.to_frame(index=False), wide.to_numpy(dtype=float)

    toy.rsrp_table = rsrp_table
    return toy


def test_top_n_and_sinr_detection_report_exactly_the_expected_beams() -> None:
    true = {(1, 7): [-70.0, -80.0, -90.0], (2, 7): [-85.0, -75.0, -100.0]}
    toy = _toy_scenario(true, {})
    table = toy.measurements
    quiet = {"accuracy_sigma_db": 0.0, "quantization_db": 0.0, "array_amp_sigma_db": 0.0, "array_phase_sigma_deg": 0.0}
    # top-2 SSB, no SINR, CSI from every cell
    cfg = FieldConfig(**quiet, ssb_detection="threshold", ssb_top_n=2, csi_serving_only=False, csi_top_n=None)
    got = report(table, toy, cfg, np.random.default_rng(0))
    ssb = got[got["beam_type"] == "ssb"].set_index(["cell_id", "beam_id"])["rsrp_dbm"]
    assert ssb.notna().to_dict() == {
        (1, 0): True,
        (1, 1): True,
        (1, 2): False,
        (2, 0): True,
        (2, 1): True,
        (2, 2): False,
    }
    # SS-SINR of beam m against the other cell's beam m (noise −120.2 dBm): γ = −6 dB
    cfg = FieldConfig(**quiet, ssb_detection="sinr", ssb_sinr_db=-6.0, csi_serving_only=True, csi_top_n=1)
    got = report(table, toy, cfg, np.random.default_rng(0))
    ssb = got[got["beam_type"] == "ssb"].set_index(["cell_id", "beam_id"])["rsrp_dbm"]
    # beam 0: 1 at +15 dB, 2 at −15 dB; beam 1: 1 at −5 dB (kept), 2 at +5 dB; beam 2: 1 at +10, 2 at −10
    assert ssb.notna().to_dict() == {
        (1, 0): True,
        (1, 1): True,
        (1, 2): True,
        (2, 0): False,
        (2, 1): True,
        (2, 2): False,
    }
    csi = got[got["beam_type"] == "csi"]
    assert set(csi["cell_id"]) == {1}  # serving cell: strongest reported SSB
    assert csi.set_index("beam_id")["rsrp_dbm"].notna().to_dict() == {0: True, 1: False, 2: False}


def test_bounds_follow_the_declared_rule_per_report() -> None:
    rsrp = {(1, 7): [-70.0, -80.0, np.nan], (2, 7): [np.nan, -75.0, np.nan], (1, 8): [-100.0, np.nan, np.nan]}
    toy = _toy_scenario(
        rsrp, {"csi": {"rule": "top_n", "top_n": 2}, "ssb": {"rule": "sinr", "detection_db": -6.0, "noise_dbm": -120.0}}
    )
    pairs, table = toy.rsrp_table(1, "csi")
    bound = missing_bounds(toy, 1, "csi", pairs, table)
    by_pair = {(int(c), int(g)): b for (c, g), b in zip(pairs.itertuples(index=False), bound, strict=True)}
    np.testing.assert_array_equal(by_pair[(1, 7)], [np.nan, np.nan, -80.0])  # full report: weakest reported
    np.testing.assert_array_equal(by_pair[(2, 7)], [-120.0, np.nan, -120.0])  # one of two: below r_th
    pairs, table = toy.rsrp_table(1, "ssb")
    bound = missing_bounds(toy, 1, "ssb", pairs, table)
    row = int(np.flatnonzero((pairs["cell_id"] == 2) & (pairs["grid_id"] == 7))[0])
    level = -6.0 + 10 * np.log10(10 ** (-70 / 10) + 10 ** (-120 / 10))  # beam 0: cell 1 at −70 dBm interferes
    assert bound[row, 0] == pytest.approx(level)
    assert bound[row, 2] == -120.0  # no interferer on beam 2: −6 dB above the noise is below r_th


def test_a_subset_keeps_the_detection_level_of_the_cells_it_left_out() -> None:
    rsrp = {(1, 7): [-70.0, -80.0, np.nan], (2, 7): [np.nan, -75.0, -90.0]}
    rule = {"ssb": {"rule": "sinr", "detection_db": -6.0, "noise_dbm": -120.0}}
    whole = _toy_scenario(rsrp, rule)
    part = _toy_scenario({(2, 7): rsrp[(2, 7)]}, rule, freq={2: 3.5e9})
    pairs, table = part.rsrp_table(1, "ssb")
    cut = missing_bounds(part, 1, "ssb", pairs, table)  # cell 1's −70 dBm on beam 0 is gone
    part.outside_ssb = pd.DataFrame(
        {"round": 1, "grid_id": 7, "freq_hz": 3.5e9, "beam_id": [0, 1], "rsrp_dbm": [-70.0, -80.0]}
    )  # what a benchmark subset carries for the cells it left out
    kept = missing_bounds(part, 1, "ssb", pairs, table)
    full_pairs, full_table = whole.rsrp_table(1, "ssb")
    full = missing_bounds(whole, 1, "ssb", full_pairs, full_table)
    row = int(np.flatnonzero((full_pairs["cell_id"] == 2).to_numpy())[0])
    np.testing.assert_allclose(kept[0], full[row])
    assert kept[0, 0] == pytest.approx(-76.0, abs=0.01) and cut[0, 0] == -120.0
    # another carrier's reports do not interfere
    part.outside_ssb = part.outside_ssb.assign(freq_hz=2.1e9)
    np.testing.assert_array_equal(missing_bounds(part, 1, "ssb", pairs, table), cut)


def test_zero_array_errors_give_the_nominal_sensing_matrix() -> None:
    grid = AngleGrid(num_el=11, num_az=12, el_min_deg=-60.0, el_step_deg=12.0)
    antenna, book, wl = CellAntenna(azimuth_deg=30.0), DFTCodebook(), 0.0857
    cfg = FieldConfig(array_amp_sigma_db=0.0, array_phase_sigma_deg=0.0)
    gains = array_errors(8, 4, cfg, np.random.default_rng(0))
    assert gains is None
    nominal = sensing_matrix(antenna, book, grid, wl, dtype=torch.float64)
    ones = torch.ones(8, 4, dtype=torch.complex128)
    torch.testing.assert_close(
        sensing_matrix(antenna, book, grid, wl, dtype=torch.float64, element_gains=ones), nominal
    )
    real = sensing_matrix(
        antenna,
        book,
        grid,
        wl,
        dtype=torch.float64,
        element_gains=array_errors(8, 4, FieldConfig(), np.random.default_rng(0)),
    )
    assert not torch.allclose(real, nominal)


def test_per_sample_fading_averages_to_the_noncoherent_expectation() -> None:
    rng = np.random.default_rng(3)
    paths = pd.DataFrame({"grid_id": np.zeros(6, dtype=np.int64), "point_id": np.zeros(6, dtype=np.int64)})
    q = rng.uniform(0.1, 1.0, (6, 5))  # [paths, beams] powers through each beam
    samples = pd.DataFrame({"grid_id": [0], "point_id": [0], "weight": [1.0]})
    expected = q.sum(0)
    errors = []
    for k in (10, 100, 10_000):
        cfg = FieldConfig(samples_per_grid=k)
        sums = SampleSums(paths, np.array([0]), samples, cfg, np.random.default_rng(k))
        np.testing.assert_allclose(sums.mean @ q, expected[None])
        errors.append(float(np.abs(10 * np.log10(sums.faded(q)[0] / expected)).max()))
    assert errors[2] < 0.2 and errors[2] < errors[0]


def test_a_real_element_pattern_changes_the_truth_only(traced: Path) -> None:
    from rflscm.antenna.msi import patch_msi_path

    sc = load_scenario(traced)
    paths = _paths(traced)
    cfg = dataclasses.replace(FieldConfig.ideal(), real_element=str(patch_msi_path()))
    _, expected, _ = field_rsrp(sc, paths, TINY.points_per_grid, cfg, np.random.default_rng(1))
    nominal = noiseless_rsrp(sc, paths, TINY.points_per_grid)
    finite = np.isfinite(nominal["rsrp_dbm"].to_numpy())
    diff = (expected["rsrp_dbm"].to_numpy() - nominal["rsrp_dbm"].to_numpy())[finite]
    assert np.abs(diff).max() > 1.0  # wider horizontally, narrower vertically, 1 dB less peak gain
    assert (sc.cells[1]["element"] == "tr38901").all()  # the models keep the declared element


def test_drive_routes_keep_only_connected_grids_along_the_routes() -> None:
    from rflscm.sim.field import drive_route

    xx, yy = np.meshgrid(np.arange(10) * 10.0 + 5, np.arange(10) * 10.0 + 5)
    grids = pd.DataFrame({"grid_id": np.arange(100), "x": xx.ravel(), "y": yy.ravel()})
    route = drive_route(grids, 1, 15, np.random.default_rng(0))
    assert 2 <= len(route) <= 15 and len(set(route)) == len(route)
    pos = grids.set_index("grid_id").loc[route, ["x", "y"]].to_numpy()
    nearest = np.sort(np.linalg.norm(pos[:, None] - pos[None], axis=-1), axis=1)[:, 1]
    assert nearest.max() <= 15.0  # every route grid touches another one: a connected street walk


def test_build_scenario_in_the_field_regime_directly(tmp_path: Path) -> None:
    cfg = dataclasses.replace(
        TINY, measurements="field", field_model=FieldConfig(samples_per_grid=6, drive_routes=1, drive_route_grids=20)
    )
    out = build_scenario(ProceduralCity(seed=2, size_m=260.0, num_buildings=14), cfg, tmp_path / "f", progress=False)
    sc = load_scenario(out)
    assert sc.meta.simulation["measurements"] == "field" and sc.meta.simulation["field"]["drive_routes"] == 1
    assert sc.meta.reporting["csi"].serving_only and check_reporting(sc) == []
    assert sc.measurements["grid_id"].nunique() <= 20  # one drive route of at most 20 grids
