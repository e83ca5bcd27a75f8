"""``rflscm check``: a valid scenario passes; every user mistake gives one line naming file/row/column and exit 2.

Most cases run ``rflscm.cli.main`` in-process (same code path as the console script, much
faster than a subprocess each); two cases run ``python -m rflscm.cli`` in a real subprocess.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from check_helpers import assert_one_line_error, run_check, table

from rflscm.data import enu_to_geodetic, read_table, write_point_cloud
from rflscm.data.examples import tiny_scenario
from rflscm.data.geo import Origin
from rflscm.data.pointcloud import PointCloud

# ---- helpers that make one mistake in the scenario folder ---------------------------------------------


def set_cell(name: str, row: int, column: str, value: object) -> Callable[[Path], None]:
    """Set data row ``row`` (1-based, as messages count) of ``column`` in table ``name``."""

    def change(df: pd.DataFrame) -> pd.DataFrame:
        try:
            df.loc[row - 1, column] = value
        except TypeError:  # pandas refuses to upcast (text or 101.5 into an int column)
            df[column] = df[column].astype(object)
            df.loc[row - 1, column] = value
        return df

    return table(name, change)


def scenario_yaml(change: Callable[[dict], None]) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        data = yaml.safe_load((root / "scenario.yaml").read_text())
        change(data)
        (root / "scenario.yaml").write_text(yaml.safe_dump(data, sort_keys=False))

    return apply


def remove(name: str) -> Callable[[Path], None]:
    return lambda root: (root / name).unlink()


def to_lat_lon(name: str) -> Callable[[Path], None]:
    def change(df: pd.DataFrame) -> pd.DataFrame:
        lat, lon, h = enu_to_geodetic(df[["x", "y", "z"]].to_numpy(), Origin(48.1, 11.6))
        return df.drop(columns=["x", "y", "z"]).assign(lat=lat, lon=lon, height_m=h)

    return table(name, change)


def empty_point_cloud(root: Path) -> None:
    write_point_cloud(PointCloud(np.zeros((0, 3)), np.zeros(0)), root / "point_cloud.ply")


M, C1, C2, G = "measurements.csv", "cells_round1.csv", "cells_round2.csv", "grids.csv"

CASES: list[tuple[str, Callable[[Path], None], list[str]]] = [
    ("missing-yaml", remove("scenario.yaml"), ["no scenario.yaml in this folder"]),
    ("missing-file", remove(G), ["scenario.yaml: `grids` = 'grids.csv': not found", "relative to the scenario folder"]),
    ("missing-round-file", remove(C2), ["`rounds.2.cells` = 'cells_round2.csv': not found"]),
    (
        "unknown-yaml-key",
        scenario_yaml(lambda d: d.update(carriers=[1])),
        ["ConfigError: scenario.yaml: unknown key(s) 'carriers'; valid keys: name, frequencies_hz"],
    ),
    ("yaml-no-round-1", scenario_yaml(lambda d: d["rounds"].pop(1)), ["`rounds` must define round 1"]),
    (
        "yaml-freq-mhz",
        scenario_yaml(lambda d: d.update(frequencies_hz=[2100, 3.5e9])),
        ["`frequencies_hz[0]` = 2100 looks like MHz; did you mean 2.1e9 Hz?"],
    ),
    (
        "yaml-bad-codebook",
        scenario_yaml(lambda d: d["codebooks"].update(x={"type": "dft", "n9": 1})),
        ["unknown key(s) 'n9' in `codebooks.x`"],
    ),
    ("empty-table", table(G, lambda df: df.iloc[:0]), ["grids.csv has no data rows"]),
    (
        "missing-column",
        table(C1, lambda df: df.drop(columns=["azimuth_deg"])),
        ["cells_round1.csv: missing column(s) `azimuth_deg`; required: cell_id, x, y, z [m]", "freq_hz"],
    ),
    (
        "misspelt-column",
        table(M, lambda df: df.rename(columns={"rsrp_dbm": "rsrp_dBm"})),
        ["measurements.csv: missing column(s) `rsrp_dbm`", "Rename `rsrp_dBm` → `rsrp_dbm`?"],
    ),
    (
        "text-in-number",
        set_cell(M, 5, "rsrp_dbm", "strong"),
        ["measurements.csv row 5 (line 6): `rsrp_dbm` = 'strong' is not a number"],
    ),
    ("decimal-comma", set_cell(G, 2, "x", "12,5"), ["grids.csv row 2 (line 3): `x` = '12,5' is not a number"]),
    ("fractional-id", set_cell(G, 3, "grid_id", 101.5), ["grids.csv row 3 (line 4): `grid_id` = 101.5 is not a whole"]),
    (
        "unknown-cell",
        set_cell(M, 7, "cell_id", 99),
        ["measurements.csv row 7 (line 8): `cell_id` = 99 is not a cell of cells_round1.csv (cell ids: 11, 12)"],
    ),
    (
        "unknown-grid",
        set_cell(M, 9, "grid_id", 999),
        ["measurements.csv row 9 (line 10): `grid_id` = 999 is not a grid of grids.csv (grid ids: 100, 101, 102)"],
    ),
    (
        "duplicate-cell",
        set_cell(C1, 2, "cell_id", 11),
        ["cells_round1.csv row 2 (line 3): `cell_id` = 11 duplicates row 1 (line 2)"],
    ),
    ("duplicate-grid", set_cell(G, 3, "grid_id", 100), ["grids.csv row 3 (line 4): `grid_id` = 100 duplicates row 1"]),
    (
        "duplicate-measurement",
        table(M, lambda df: pd.concat([df.iloc[:4], df.iloc[[1]], df.iloc[4:]])),
        [
            "measurements.csv row 5 (line 6): (`round`, `cell_id`, `grid_id`, `beam_type`, `beam_id`) = "
            "(1, 11, 100, 'ssb', 1) duplicates row 2 (line 3)"
        ],
    ),
    ("nan-grid-coordinate", set_cell(G, 2, "y", np.nan), ["grids.csv row 2 (line 3): `y` is empty (NaN)"]),
    ("nan-cell-coordinate", set_cell(C1, 1, "z", np.nan), ["cells_round1.csv row 1 (line 2): `z` is empty (NaN)"]),
    (
        "rsrp-too-high",
        set_cell(M, 3, "rsrp_dbm", 12.0),
        [
            "measurements.csv row 3 (line 4): `rsrp_dbm` = 12.0 is outside the reportable range −156…−31 dBm "
            "(values in W or mW? convert to dBm)."
        ],
    ),
    ("rsrp-sentinel", set_cell(M, 4, "rsrp_dbm", -999.0), ["`rsrp_dbm` = -999.0 is outside", "not a sentinel"]),
    (
        "freq-in-mhz",
        set_cell(C1, 1, "freq_hz", 3500),
        ["cells_round1.csv row 1 (line 2): `freq_hz` = 3500.0 looks like MHz; did you mean 3.5e9 Hz?"],
    ),
    ("freq-in-ghz", set_cell(C1, 2, "freq_hz", 2.1), ["`freq_hz` = 2.1 looks like GHz; did you mean 2.1e9 Hz?"]),
    (
        "freq-not-a-carrier",
        set_cell(C1, 2, "freq_hz", 2.6e9),
        [
            "cells_round1.csv row 2 (line 3): `freq_hz` = 2600000000.0 is not a carrier of scenario.yaml "
            "`frequencies_hz` (2.1e9, 3.5e9)"
        ],
    ),
    (
        "mech-tilt",
        set_cell(C1, 2, "mech_tilt_deg", 95.0),
        [
            "cells_round1.csv row 2 (line 3): `mech_tilt_deg` = 95.0 is outside −90…90° "
            "(tilt in degrees, positive = down)"
        ],
    ),
    (
        "elec-tilt",
        set_cell(C2, 1, "elec_tilt_deg", -120.0),
        ["cells_round2.csv row 1 (line 2): `elec_tilt_deg` = -120.0 is outside −90…90°"],
    ),
    (
        "azimuth-negative",
        set_cell(C1, 1, "azimuth_deg", -30.0),
        ["cells_round1.csv row 1 (line 2): `azimuth_deg` = -30.0 is outside 0…360°", "add 360"],
    ),
    ("azimuth-too-big", set_cell(C1, 2, "azimuth_deg", 400.0), ["`azimuth_deg` = 400.0 is outside 0…360°"]),
    (
        "unknown-codebook",
        set_cell(C1, 2, "csi_codebook", "csi32"),
        [
            "cells_round1.csv row 2 (line 3): `csi_codebook` = 'csi32' is not a codebook of scenario.yaml `codebooks`; "
            "valid: ssb8, csi8"
        ],
    ),
    (
        "codebook-does-not-fit",
        table(C1, lambda df: df.assign(array_nh=[8, 4])),
        [
            "cells_round1.csv row 2 (line 3): `csi_codebook` = 'csi8' does not fit this cell's array: DFT codebook "
            "N1 × N2 = 8 × 4 does not match the 4 × 4 array"
        ],
    ),
    (
        "beam-id-too-big",
        set_cell(M, 6, "beam_id", 8),
        [
            "measurements.csv row 6 (line 7): `beam_id` = 8 is out of range for cell 11 in round 1: its ssb codebook "
            "'ssb8' has 8 beams (beam_id 0…7"
        ],
    ),
    ("beam-id-negative", set_cell(M, 6, "beam_id", -1), ["row 6 (line 7): `beam_id` = -1 must be ≥ 0"]),
    (
        "beam-type",
        set_cell(M, 2, "beam_type", "ssb1"),
        ["measurements.csv row 2 (line 3): `beam_type` = 'ssb1' is not one of 'ssb', 'csi'"],
    ),
    (
        "round-without-cells",
        set_cell(M, 10, "round", 3),
        ["measurements.csv row 10 (line 11): `round` = 3 has no cells table; scenario.yaml `rounds` defines 1, 2"],
    ),
    (
        "round2-missing-cell",
        table(C2, lambda df: df.iloc[:1]),
        ["cells_round2.csv: cell(s) 12 of round 1 (cells_round1.csv) are missing; every round lists the same cells"],
    ),
    (
        "round2-extra-cell",
        set_cell(C2, 2, "cell_id", 13),
        ["cells_round2.csv row 2 (line 3): `cell_id` = 13 is not a cell of round 1 (cells_round1.csv)"],
    ),
    (
        "round2-moved",
        set_cell(C2, 2, "x", 5.0),
        ["cells_round2.csv row 2 (line 3): `x` = 5.0 differs from round 1 (cells_round1.csv: 0.0) for cell 12"],
    ),
    ("round2-other-carrier", set_cell(C2, 1, "freq_hz", 2.1e9), ["`freq_hz` = 2100000000.0 differs from round 1"]),
    ("empty-point-cloud", empty_point_cloud, ["point_cloud.ply has no points"]),
    ("lat-lon-without-origin", to_lat_lon(G), ["grids.csv: gives lat/lon/height_m but scenario.yaml has no `origin`"]),
    (
        "missing-element-file",
        set_cell(C1, 1, "element", "ant/panel.msi"),
        ["cells_round1.csv row 1 (line 2): `element` = 'ant/panel.msi': file not found"],
    ),
    ("spacing-in-wavelengths", set_cell(C1, 1, "spacing_h_m", 0.5), ["`spacing_h_m` = 0.5 is more than 2 wavelengths"]),
    (
        "semicolon-csv",
        lambda root: (root / G).write_text("grid_id;x;y;z\n100;1;2;1.5\n"),
        ["grids.csv: missing column(s) `grid_id`", "looks ';'-separated; save the file as comma-separated CSV"],
    ),
    (
        "broken-yaml",
        lambda root: (root / "scenario.yaml").write_text("name: [unclosed\ngrids: g.csv\n"),
        ["ConfigError: ", "scenario.yaml: not valid YAML"],
    ),
    (
        "tx-power-in-watts-or-mw",
        set_cell(C1, 2, "tx_power_dbm", 20000.0),
        ["cells_round1.csv row 2 (line 3): `tx_power_dbm` = 20000.0 is outside the plausible -20…40 dBm"],
    ),
    (
        "lat-out-of-range",
        lambda root: [
            scenario_yaml(lambda d: d.update(origin={"lat": 48.1, "lon": 11.6}))(root),
            to_lat_lon(G)(root),
            set_cell(G, 2, "lat", 148.1)(root),
        ],
        ["grids.csv row 2 (line 3): `lat` = 148.1 must lie in −90…90°"],
    ),
    (
        "lat-lon-swapped",
        lambda root: [
            scenario_yaml(lambda d: d.update(origin={"lat": 48.1, "lon": 11.6}))(root),
            to_lat_lon(G)(root),
            table(G, lambda df: df.rename(columns={"lat": "lon", "lon": "lat"}))(root),
        ],
        ["grids.csv row 1 (line 2): `lat` = 11.6", "km from the origin (48.1, 11.6); are lat and lon swapped"],
    ),
    ("infinite", set_cell(M, 2, "rsrp_dbm", np.inf), ["row 2 (line 3): `rsrp_dbm` = inf is infinite"]),
]


@pytest.mark.parametrize(("mistake", "expected"), [(c[1], c[2]) for c in CASES], ids=[c[0] for c in CASES])
def test_user_mistake_gives_one_line_and_exit_2(
    scenario_dir: Path,
    mistake: Callable[[Path], None],
    expected: list[str],
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    mistake(scenario_dir)
    assert_one_line_error(*run_check(scenario_dir, monkeypatch, capsys), expected)


def test_parquet_rows_have_no_line_numbers(tmp_path: Path, monkeypatch, capsys) -> None:
    root = tiny_scenario(tmp_path / "pq", table_format="parquet")
    set_cell("measurements.parquet", 17, "rsrp_dbm", -20.0)(root)
    code, _, err = run_check(root, monkeypatch, capsys)
    assert code == 2
    assert err.strip() == (
        "DataError: measurements.parquet row 17: `rsrp_dbm` = -20.0 is outside the reportable range −156…−31 dBm "
        "(values in W or mW? convert to dBm)."
    )


def test_many_bad_rows_are_counted(scenario_dir: Path, monkeypatch, capsys) -> None:
    table(M, lambda df: df.assign(rsrp_dbm=df["rsrp_dbm"].fillna(-80.0) + 100.0))(scenario_dir)
    code, _, err = run_check(scenario_dir, monkeypatch, capsys)
    n = len(read_table(scenario_dir / M))
    assert code == 2 and "row 1 (line 2)" in err and f"{n - 1} more row(s) have the same problem." in err


def test_valid_scenario_summary(scenario_dir: Path, monkeypatch, capsys) -> None:
    code, out, err = run_check(scenario_dir, monkeypatch, capsys)
    assert code == 0, err
    assert "tiny" in out and "OK" in out
    assert "cells: 2 on 1 site(s) (2.1 GHz: 1, 3.5 GHz: 1)" in out
    assert "grids: 3" in out and "threshold: -120 dBm" in out
    assert "point cloud: 3 points (ground 33 %, building 67 %)" in out
    m = read_table(scenario_dir / M)
    sel = (m["round"] == 1) & (m["beam_type"] == "ssb")
    missing = f"{100 * m.loc[sel, 'rsrp_dbm'].isna().mean():.1f} %"
    rows = [[cell.strip() for cell in line.split("│")[1:-1]] for line in out.splitlines() if line.startswith("│")]
    assert ["1", "ssb", str(int(sel.sum())), "6", "2", "3", missing] in rows, out


def test_subprocess_end_to_end(scenario_dir: Path) -> None:
    command = [sys.executable, "-m", "rflscm.cli", "check", str(scenario_dir / "scenario.yaml")]
    ok = subprocess.run(command, capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert "OK" in ok.stdout
    set_cell(M, 3, "rsrp_dbm", 12.0)(scenario_dir)
    bad = subprocess.run(
        [sys.executable, "-m", "rflscm.cli", "check", str(scenario_dir)], capture_output=True, text=True, timeout=120
    )
    assert bad.returncode == 2
    assert "Traceback" not in bad.stderr
    assert bad.stderr.strip().splitlines() == [
        "DataError: measurements.csv row 3 (line 4): `rsrp_dbm` = 12.0 is outside the reportable range "
        "−156…−31 dBm (values in W or mW? convert to dBm)."
    ]
