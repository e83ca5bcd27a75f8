"""Scenario: normalisation, save/load, fingerprint, RSRP table, antenna and sensing views."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch

from rflscm.antenna import (
    SPEED_OF_LIGHT,
    ArrayGeometry,
    CellAntenna,
    DFTCodebook,
    MeasuredElement,
    SSBCodebook,
    TR38901Element,
    sensing_matrix,
    write_msi,
)
from rflscm.data import CELL_COLUMNS, MEASUREMENT_COLUMNS, Scenario, load_scenario, read_table, save_scenario
from rflscm.errors import ConfigError, DataError
from rflscm.geometry import AngleGrid


def test_tiny_scenario_contents(tiny: Scenario) -> None:
    assert tiny.rounds() == [1, 2]
    np.testing.assert_array_equal(tiny.cell_ids(), [11, 12])
    np.testing.assert_array_equal(tiny.grid_ids(), [100, 101, 102])
    assert tiny.meta.frequencies_hz == (2.1e9, 3.5e9)  # written as `2.1e9` (PyYAML reads it as text)
    assert isinstance(tiny.meta.codebooks["ssb8"], SSBCodebook)
    assert isinstance(tiny.meta.codebooks["csi8"], DFTCodebook)
    assert tiny.point_cloud is not None and tiny.point_cloud.class_counts() == {2: 1, 6: 2}
    m = tiny.measurements
    assert list(m.columns) == list(MEASUREMENT_COLUMNS)
    assert m["rsrp_dbm"].isna().any() and m["rsrp_dbm"].notna().any()
    assert set(m["round"]) == {1, 2} and set(m["beam_type"]) == {"ssb", "csi"}


def test_cells_are_normalised_with_defaults(tiny_dir: Path, edit_table) -> None:
    edit_table(tiny_dir / "cells_round1.csv", lambda df: df.iloc[::-1])  # ids in reverse order in the file
    sc = load_scenario(tiny_dir)
    cells = sc.cells[1]
    assert list(cells.columns) == list(CELL_COLUMNS)
    assert cells["cell_id"].tolist() == [11, 12] and list(cells.index) == [0, 1]
    assert cells["tx_power_dbm"].tolist() == [15.0, 15.0]
    assert cells["array_nh"].tolist() == [8, 8] and cells["array_nv"].tolist() == [4, 4]
    wavelength = SPEED_OF_LIGHT / np.array([3.5e9, 2.1e9])
    np.testing.assert_allclose(cells["spacing_h_m"], 0.5 * wavelength)
    np.testing.assert_allclose(cells["spacing_v_m"], 0.7 * wavelength)
    assert cells["element"].tolist() == ["tr38901", "tr38901"]
    for column, dtype in (("cell_id", "int64"), ("x", "float64"), ("array_nh", "int64"), ("freq_hz", "float64")):
        assert cells[column].dtype == dtype
    assert sc.cells[2]["mech_tilt_deg"].tolist() == [4.0, 8.0]


def test_partial_optional_columns_take_defaults_per_row(tiny_dir: Path, edit_table) -> None:
    def change(df: pd.DataFrame) -> None:
        df["tx_power_dbm"] = [18.0, np.nan]
        df["array_nh"] = [np.nan, 8]

    edit_table(tiny_dir / "cells_round1.csv", change)
    cells = load_scenario(tiny_dir).cells[1]
    assert cells["tx_power_dbm"].tolist() == [18.0, 15.0]
    assert cells["array_nh"].tolist() == [8, 8] and cells["array_nh"].dtype == "int64"


@pytest.mark.parametrize("table_format", ["parquet", "csv"])
def test_save_load_round_trip(tiny: Scenario, tmp_path: Path, table_format: str) -> None:
    out = save_scenario(tiny, tmp_path / "copy", table_format=table_format)
    back = load_scenario(out)
    assert back == tiny
    assert back.fingerprint() == tiny.fingerprint()
    suffix = ".parquet" if table_format == "parquet" else ".csv"
    assert back.meta.grids == f"grids{suffix}" and back.meta.rounds == {
        1: f"cells_round1{suffix}",
        2: f"cells_round2{suffix}",
    }
    assert back.meta.simulation == tiny.meta.simulation
    # a second generation is identical too (the written form is a fixed point)
    again = load_scenario(save_scenario(back, tmp_path / "again", table_format="csv"))
    assert again == tiny and load_scenario(out / "scenario.yaml") == tiny


def test_fingerprint_tracks_round1_data_only(tiny: Scenario) -> None:
    m = tiny.measurements
    reported_round1 = np.flatnonzero(((m["round"] == 1) & m["rsrp_dbm"].notna()).to_numpy())[0]
    reported_round2 = np.flatnonzero(((m["round"] == 2) & m["rsrp_dbm"].notna()).to_numpy())[0]
    changed1 = m.copy()
    changed1.loc[reported_round1, "rsrp_dbm"] -= 1.0
    changed2 = m.copy()
    changed2.loc[reported_round2, "rsrp_dbm"] -= 1.0
    assert tiny.with_measurements(changed1).fingerprint() != tiny.fingerprint()
    assert tiny.with_measurements(changed2).fingerprint() == tiny.fingerprint()
    assert len(tiny.fingerprint()) == 64


def test_rsrp_table_layout(tiny_dir: Path, edit_table, edit_yaml) -> None:
    """Cell 12 gets a 4-beam CSI codebook; pair (11, 101) has no SSB rows at all."""
    edit_yaml(tiny_dir, lambda d: d["codebooks"].update(csi4={"type": "dft", "beams_h": [-1, 1], "beams_v": [0, 2]}))
    for r in (1, 2):
        edit_table(tiny_dir / f"cells_round{r}.csv", lambda df: df.assign(csi_codebook=["csi8", "csi4"]))

    def drop(df: pd.DataFrame) -> pd.DataFrame:
        small = (df["cell_id"] == 12) & (df["beam_type"] == "csi") & (df["beam_id"] >= 4)
        gone = (df["cell_id"] == 11) & (df["grid_id"] == 101) & (df["beam_type"] == "ssb") & (df["round"] == 1)
        return df[~(small | gone)]

    edit_table(tiny_dir / "measurements.csv", drop)
    sc = load_scenario(tiny_dir)
    pairs, ssb = sc.rsrp_table(1, "ssb")
    assert ssb.shape == (5, 8) and ssb.dtype == np.float64
    assert list(pairs.itertuples(index=False, name=None)) == [(11, 100), (11, 102), (12, 100), (12, 101), (12, 102)]
    pairs, csi = sc.rsrp_table(1, "csi")
    assert csi.shape == (6, 8)
    assert np.isnan(csi[pairs["cell_id"].to_numpy() == 12, 4:]).all()
    # independent reconstruction from the long table, row by row
    m = sc.measurements
    for (cell_id, grid_id), row in zip(pairs.itertuples(index=False, name=None), csi, strict=True):
        sel = m[(m["round"] == 1) & (m["beam_type"] == "csi") & (m["cell_id"] == cell_id) & (m["grid_id"] == grid_id)]
        expected = np.full(8, np.nan)
        expected[sel["beam_id"].to_numpy()] = sel["rsrp_dbm"].to_numpy()
        np.testing.assert_array_equal(row, expected)
    with pytest.raises(ConfigError, match="beam type must be one of ssb, csi"):
        sc.rsrp_table(1, "prs")
    with pytest.raises(DataError, match="round 3 has no cells table"):
        sc.rsrp_table(3, "ssb")


def test_antenna_and_sensing_match_the_antenna_package(tiny: Scenario) -> None:
    row = read_table(tiny.root / "cells_round2.csv").set_index("cell_id").loc[12]
    wavelength = SPEED_OF_LIGHT / 2.1e9
    expected_antenna = CellAntenna(
        azimuth_deg=row["azimuth_deg"],
        mech_tilt_deg=row["mech_tilt_deg"],
        elec_tilt_deg=row["elec_tilt_deg"],
        array=ArrayGeometry.for_frequency(2.1e9),
        element=TR38901Element(),
        tx_power_dbm=15.0,
    )
    antenna = tiny.antenna(12, round=2)
    assert antenna.azimuth_deg == 180.0 and antenna.mech_tilt_deg == 8.0
    assert antenna.array.num_h == 8 and antenna.array.spacing_h_m == pytest.approx(0.5 * wavelength)
    grid = AngleGrid.full_sphere(7, 12)
    codebook = DFTCodebook(beams_h=(-3, -1, 1, 3), beams_v=(0, 2))
    expected = sensing_matrix(expected_antenna, codebook, grid, wavelength, dtype=torch.float64)
    got = tiny.sensing(12, "csi", grid, round=2, dtype=torch.float64)
    assert got.shape == (8, 84)
    torch.testing.assert_close(got, expected, rtol=1e-12, atol=0)
    # round 1 differs (tilt changed), and beam types pick their own codebook
    assert not torch.allclose(tiny.sensing(12, "csi", grid, round=1, dtype=torch.float64), got)
    assert tiny.sensing(11, "ssb", grid).shape == (8, 84) and tiny.num_beams(11, "SSB") == 8
    np.testing.assert_array_equal(tiny.cell_position(11), [0.0, 0.0, 25.0])
    assert tiny.freq_hz(11) == 3.5e9 and tiny.wavelength_m(11) == pytest.approx(SPEED_OF_LIGHT / 3.5e9)
    with pytest.raises(DataError, match=r"cell_id 5 is not a cell of this scenario \(cell ids: 11, 12\)"):
        tiny.antenna(5)


def test_measured_element_from_msi_file(tiny_dir: Path, edit_table, tmp_path: Path) -> None:
    element = MeasuredElement(
        max_gain_dbi=17.0, horizontal_loss_db=tuple(np.linspace(0, 30, 36)), vertical_loss_db=(0.0,) * 36, name="p"
    )
    (tiny_dir / "patterns").mkdir()
    write_msi(element, tiny_dir / "patterns" / "panel.msi")
    edit_table(tiny_dir / "cells_round1.csv", lambda df: df.assign(element=["patterns/panel.msi", ""]))
    sc = load_scenario(tiny_dir)
    assert isinstance(sc.antenna(11).element, MeasuredElement)
    assert sc.antenna(11).element.max_gain_dbi == pytest.approx(17.0)
    assert isinstance(sc.antenna(12).element, TR38901Element)
    copy = load_scenario(save_scenario(sc, tmp_path / "copy"))  # the pattern file travels with the scenario
    assert (tmp_path / "copy" / "patterns" / "panel.msi").is_file()
    assert copy == sc and copy.antenna(11).element == sc.antenna(11).element


def test_with_measurements_validates(tiny: Scenario) -> None:
    half = tiny.measurements.iloc[::2]
    sub = tiny.with_measurements(half)
    assert len(sub.measurements) == len(half) and sub.grids is tiny.grids
    assert list(sub.measurements.index) == list(range(len(half)))
    assert len(tiny.measurements) == 2 * len(half)  # the original is untouched
    bad = half.copy()
    bad.iloc[2, bad.columns.get_loc("grid_id")] = 7
    with pytest.raises(DataError, match=r"measurements \(replacement table\) row 3: `grid_id` = 7 is not a grid"):
        tiny.with_measurements(bad)


def test_scenario_without_measurements_or_point_cloud(tiny_dir: Path, edit_yaml, tmp_path: Path) -> None:
    edit_yaml(tiny_dir, lambda d: [d.pop("measurements"), d.pop("point_cloud")])
    sc = load_scenario(tiny_dir)
    assert len(sc.measurements) == 0 and sc.point_cloud is None
    pairs, rsrp = sc.rsrp_table(1, "ssb")
    assert len(pairs) == 0 and rsrp.shape == (0, 8)
    assert load_scenario(save_scenario(sc, tmp_path / "copy")) == sc


def test_truth_folder_is_copied(tiny_dir: Path, edit_yaml, tmp_path: Path) -> None:
    (tiny_dir / "truth").mkdir()
    (tiny_dir / "truth" / "paths.parquet").write_bytes(b"x")
    edit_yaml(tiny_dir, lambda d: d.update(truth="truth"))
    sc = load_scenario(tiny_dir)
    out = save_scenario(sc, tmp_path / "copy")
    assert (out / "truth" / "paths.parquet").read_bytes() == b"x"
    assert load_scenario(out).meta.truth == "truth"
    shutil.rmtree(tiny_dir / "truth")
    with pytest.raises(DataError, match=r"`truth` = 'truth': not found"):
        load_scenario(tiny_dir)


def test_outside_ssb_is_part_of_equality_and_of_the_round_1_fingerprint(tiny: Scenario) -> None:
    import dataclasses

    def cut(rounds: list[int]) -> Scenario:
        table = pd.DataFrame({"round": rounds, "grid_id": 1, "freq_hz": 3.5e9, "beam_id": 0, "rsrp_dbm": -80.0})
        return dataclasses.replace(tiny, outside_ssb=table)

    assert cut([1]) != tiny and cut([1]) == cut([1]) and cut([1]) != cut([2])
    assert cut([1]).fingerprint() != tiny.fingerprint()  # it sets the training data's detection bounds
    assert cut([2]).fingerprint() == cut([2, 2]).fingerprint() != cut([1, 2]).fingerprint()  # round 1 only


def test_loading_without_measurements_leaves_them_unread(tiny_dir: Path) -> None:
    full = load_scenario(tiny_dir)
    lean = load_scenario(tiny_dir, measurements=False)
    assert len(full.measurements) > 0 and len(lean.measurements) == 0
    assert list(lean.measurements.columns) == list(full.measurements.columns)
    pd.testing.assert_frame_equal(lean.cells[1], full.cells[1])
    pd.testing.assert_frame_equal(lean.grids, full.grids)
    (tiny_dir / "measurements.csv").write_text("not, a, table\n")  # never opened
    assert len(load_scenario(tiny_dir, measurements=False).measurements) == 0
    with pytest.raises(DataError):
        load_scenario(tiny_dir)
