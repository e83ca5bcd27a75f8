"""Issue 14: scenarios a user may feed ``rflscm check``, each built from a case that once went wrong.

Every case ends in exit 2 with ONE stderr line naming the file and the problem (or exit 0 with the right
behaviour), never a traceback.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml
from check_helpers import assert_one_line_error, run_check, table

from rflscm.cli import main
from rflscm.data import read_table, write_point_cloud
from rflscm.data.pointcloud import PointCloud, read_point_cloud

M, C1, C2, G, Y = "measurements.csv", "cells_round1.csv", "cells_round2.csv", "grids.csv", "scenario.yaml"


def both_rounds(change: Callable[[pd.DataFrame], pd.DataFrame | None]) -> Callable[[Path], None]:
    return lambda root: [table(name, change)(root) for name in (C1, C2)]


def text_edit(name: str, change: Callable[[str], str]) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        path = root / name
        path.write_text(change(path.read_text()))

    return apply


def raw(name: str, change: Callable[[bytes], bytes]) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        path = root / name
        path.write_bytes(change(path.read_bytes()))

    return apply


def replace_line(name: str, line: int, new: str) -> Callable[[Path], None]:
    """Replace text-editor line ``line`` (1 = header) of a CSV file."""

    def change(text: str) -> str:
        lines = text.splitlines()
        lines[line - 1] = new
        return "\n".join(lines) + "\n"

    return text_edit(name, change)


def codebooks(change: Callable[[dict], None]) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        data = yaml.safe_load((root / Y).read_text())
        change(data["codebooks"])
        (root / Y).write_text(yaml.safe_dump(data, sort_keys=False))

    return apply


def yaml_edit(change: Callable[[dict], None]) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        data = yaml.safe_load((root / Y).read_text())
        change(data)
        (root / Y).write_text(yaml.safe_dump(data, sort_keys=False))

    return apply


def shift_cloud(dx: float, dz: float = 0.0) -> Callable[[Path], None]:
    def apply(root: Path) -> None:
        pc = read_point_cloud(root / "point_cloud.ply")
        write_point_cloud(PointCloud(pc.xyz + np.array([dx, 0.0, dz]), pc.classification), root / "point_cloud.ply")

    return apply


def utm(df: pd.DataFrame) -> pd.DataFrame:
    return df.assign(x=df["x"] + 691_000.0, y=df["y"] + 5_334_000.0)


def set_value(name: str, row: int, column: str, value: object) -> Callable[[Path], None]:
    def change(df: pd.DataFrame) -> pd.DataFrame:
        df[column] = df[column].astype(object) if column in df.columns else None
        df.loc[row - 1, column] = value
        return df

    return table(name, change)


CASES: list[tuple[str, Callable[[Path], None], list[str]]] = [
    # item 1: plausibility
    (
        "utm-cells",
        both_rounds(utm),
        ["cells_round1.csv row 1 (line 2): `x` = 691000.0 puts the point more than 200 km", "UTM"],
    ),
    ("utm-grids", table(G, utm), ["grids.csv row 1 (line 2)", "more than 200 km from the frame's origin"]),
    ("coordinate-1e308", set_value(G, 2, "x", 1e308), ["grids.csv row 2 (line 3): `x` = 1e+308 puts the point"]),
    (
        "cells-far-from-grids",
        both_rounds(lambda df: df.assign(x=df["x"] + 60_000.0)),
        ["cells_round1.csv and grids.csv do not cover the same place: they are 60 km apart horizontally"],
    ),
    (
        "point-cloud-elsewhere",
        shift_cloud(20_000.0),
        [
            "cells_round1.csv and point_cloud.ply do not cover the same place: they are 20 km apart horizontally "
            "(at most 5 km)"
        ],
    ),
    ("point-cloud-utm", shift_cloud(5_000_000.0), ["point_cloud.ply point 1", "implausible", "UTM"]),
    (
        "cell-height-in-mm",
        both_rounds(lambda df: df.assign(z=25_000.0)),
        ["cells_round1.csv row 1 (line 2): `z` = 25000.0 is outside the plausible -500…9000 m"],
    ),
    ("grid-height-far-below", table(G, lambda df: df.assign(z=-3000.0)), ["`z` = -3000.0 is outside the plausible"]),
    (
        "cells-high-above-grids",
        both_rounds(lambda df: df.assign(z=5000.0)),
        ["cells_round1.csv and grids.csv do not cover the same place", "m apart vertically (at most 2000 m)"],
    ),
    (
        "rs-power-too-high",
        set_value(C1, 1, "tx_power_dbm", 46.0),
        ["cells_round1.csv row 1 (line 2): `tx_power_dbm` = 46.0 is outside the plausible -20…40 dBm"],
    ),
    ("rs-power-too-low", set_value(C1, 2, "tx_power_dbm", -25.0), ["`tx_power_dbm` = -25.0 is outside the plausible"]),
    # item 2: scenario.yaml not UTF-8
    (
        "yaml-latin1",
        raw(Y, lambda b: b.replace(b"description: ", b"description: caf\xe9 ")),
        ["scenario.yaml line 2: byte 0xe9 is not UTF-8 text; save the file as UTF-8"],
    ),
    ("yaml-utf16", raw(Y, lambda b: b.decode().encode("utf-16")), ["scenario.yaml", "not UTF-8"]),
    # item 3: missing required fields
    (
        "origin-without-lon",
        yaml_edit(lambda d: d.update(origin={"lat": 48.14})),
        ["scenario.yaml: `origin` is missing required key(s) 'lon'"],
    ),
    (
        "origin-lat-nan",
        yaml_edit(lambda d: d.update(origin={"lat": float("nan"), "lon": 11.0})),
        ["scenario.yaml: `origin.lat` must be a number (got .nan)"],
    ),
    # item 8: values that are not numbers are counted, short and truncated rows refused
    (
        "rsrp-na-tokens",
        lambda root: [
            set_value(M, r, "rsrp_dbm", t)(root) for r, t in ((2, "N/A"), (3, "None"), (5, "null"), (8, "#N/A"))
        ],
        ["measurements.csv row 2 (line 3): `rsrp_dbm` = 'N/A' is not a number", "3 more row(s) have the same problem"],
    ),
    ("rsrp-nan-text", set_value(M, 4, "rsrp_dbm", "NaN"), ["row 4 (line 5): `rsrp_dbm` = 'NaN' is not a number"]),
    (
        "short-row",
        replace_line(M, 7, "1,11,100,ssb,5"),
        ["measurements.csv line 7: 5 field(s) where the header has 6; the row is cut short"],
    ),
    (
        "truncated-file",
        raw(M, lambda b: b[: len(b) - 9]),
        ["measurements.csv line 193:", "the file ends in the middle of this row (was it cut off?)"],
    ),
    (
        "long-row",
        replace_line(G, 3, "101,-40,5,-90.0,1.5"),
        ["grids.csv line 3: 5 field(s) where the header has 4; an extra comma, or a decimal comma"],
    ),
    ("unclosed-quote", replace_line(G, 4, '102,"5,1,1.5'), ["grids.csv line 4:", "quote"]),
    # item 9: misspelled optional columns
    (
        "misspelt-optional",
        table(C1, lambda df: df.assign(tx_power_dBm=[20.0, 20.0])),
        ["cells_round1.csv: column `tx_power_dBm` is not a column rflscm knows; did you mean `tx_power_dbm`?"],
    ),
    ("misspelt-array", both_rounds(lambda df: df.assign(array_nhh=[8, 8])), ["did you mean `array_nh`?"]),
    # item 10: duplicates
    (
        "duplicate-csv-header",
        text_edit(G, lambda t: t.replace("grid_id,x,y,z", "grid_id,x,y,x", 1)),
        ["grids.csv line 1: column `x` appears twice in the header"],
    ),
    (
        "duplicate-yaml-key",
        text_edit(Y, lambda t: t + "name: other\n"),
        ["scenario.yaml line", "key 'name' appears twice in the same mapping (first on line 1)"],
    ),
    (
        "duplicate-nested-yaml-key",
        text_edit(Y, lambda t: t.replace("{type: dft,", "{type: dft, type: ssb,", 1)),
        ["key 'type' appears twice"],
    ),
    # item 11: codebook contents
    (
        "ssb-azimuth-200",
        codebooks(lambda c: c["ssb8"].update(azimuths_deg=[-45.0, 200.0])),
        ["`codebooks.ssb8`", "`azimuths_deg` = 200.0 is outside −180…180°"],
    ),
    (
        "ssb-tilt-95",
        codebooks(lambda c: c["ssb8"].update(tilts_deg=[95.0])),
        ["`codebooks.ssb8`", "`tilts_deg` = 95.0"],
    ),
    ("ssb-nan-azimuth", codebooks(lambda c: c["ssb8"].update(azimuths_deg=[float("nan")])), ["`codebooks.ssb8"]),
    (
        "ssb-duplicate-beams",
        codebooks(lambda c: c["ssb8"].update(azimuths_deg=[15.0, 15.0])),
        ["`codebooks.ssb8`", "lists 15.0 twice"],
    ),
    ("ssb-zero-beams", codebooks(lambda c: c["ssb8"].update(tilts_deg=[])), ["`codebooks.ssb8`", "at least one"]),
    (
        "dft-index-beyond",
        codebooks(lambda c: c["csi8"].update(beams_h=[0, 16])),
        ["`codebooks.csi8`", "`beams_h` = 16 is beyond the 16 DFT beams"],
    ),
    (
        "dft-aliased-beams",
        codebooks(lambda c: c["csi8"].update(beams_h=[-1, 15])),
        ["`codebooks.csi8`", "lists the beam 15 twice"],
    ),
    ("dft-zero-beams", codebooks(lambda c: c["csi8"].update(beams_v=[])), ["`codebooks.csi8`", "at least one"]),
    # item 12: messages that blamed the wrong thing
    (
        "cell-id-beyond-int64",
        both_rounds(
            lambda df: df.assign(cell_id=df["cell_id"].astype(object)).assign(cell_id=[99999999999999999999, 12])
        ),
        ["cells_round1.csv row 1 (line 2): `cell_id` = 99999999999999999999 is too large"],
    ),
    (
        "csv-latin1",
        raw(G, lambda b: b.replace(b"101,", b"10\xe9,")),
        ["grids.csv row 2 (line 3): byte 0xe9 is not UTF-8 text"],
    ),
    (
        "table-is-a-folder",
        lambda root: [(root / G).unlink(), (root / G).mkdir()],
        ["scenario.yaml: `grids` = 'grids.csv' is a folder"],
    ),
    (
        "point-cloud-is-a-folder",
        lambda root: [(root / "point_cloud.ply").unlink(), (root / "point_cloud.ply").mkdir()],
        ["`point_cloud` = 'point_cloud.ply' is a folder"],
    ),
    ("yaml-is-a-folder", lambda root: [(root / Y).unlink(), (root / Y).mkdir()], ["scenario.yaml", "folder"]),
    ("nul-bytes", raw(M, lambda b: b.replace(b"-6", b"\x00-6", 1)), ["measurements.csv line", "NUL byte"]),
    ("csv-utf16", raw(G, lambda b: b.decode().encode("utf-16")), ["grids.csv: the file is UTF-16 encoded"]),
    (
        "parquet-garbage",
        lambda root: [
            yaml_edit(lambda d: d.update(grids="grids.parquet"))(root),
            (root / "grids.parquet").write_bytes(b"PAR1 not really"),
        ],
        ["grids.parquet: not a readable Parquet file"],
    ),
]


@pytest.mark.parametrize(("mistake", "expected"), [(c[1], c[2]) for c in CASES], ids=[c[0] for c in CASES])
def test_malformed_scenario_gives_one_line_and_exit_2(
    scenario_dir: Path, mistake: Callable[[Path], None], expected: list[str], monkeypatch, capsys
) -> None:
    mistake(scenario_dir)
    assert_one_line_error(*run_check(scenario_dir, monkeypatch, capsys), expected)


def test_unused_column_is_listed_as_ignored(scenario_dir: Path, monkeypatch, capsys) -> None:
    table(G, lambda df: df.assign(comment="roof"))(scenario_dir)
    code, out, err = run_check(scenario_dir, monkeypatch, capsys)
    assert code == 0, err
    assert "grids.csv: column(s) `comment` are not used by rflscm (ignored)" in " ".join(out.split())


def test_blank_lines_keep_line_numbers_right(scenario_dir: Path, monkeypatch, capsys) -> None:
    text_edit(G, lambda t: t.replace("\n", "\n\n", 2))(scenario_dir)  # blank lines after the header and row 1
    code, out, _ = run_check(scenario_dir, monkeypatch, capsys)
    assert code == 0 and "grids.csv 3" in out
    set_value(G, 2, "x", "east")(scenario_dir)
    text_edit(G, lambda t: t.replace("\n", "\n\n", 2))(scenario_dir)
    code, _, err = run_check(scenario_dir, monkeypatch, capsys)
    assert code == 2 and "grids.csv row 2 (line 5): `x` = 'east' is not a number" in err, err


def test_unreadable_file(scenario_dir: Path, monkeypatch, capsys) -> None:
    import os

    real = os.open

    def deny(path, flags, *args, **kwargs):  # files are opened with os.open (non-blocking, regular files only)
        if Path(path).name == G:
            raise PermissionError(13, "Permission denied")
        return real(path, flags, *args, **kwargs)

    monkeypatch.setattr(os, "open", deny)
    code, _, err = run_check(scenario_dir, monkeypatch, capsys)
    assert code == 2 and "grids.csv: cannot read the table file (permission denied)" in err, err


def test_empty_field_still_means_not_reported(scenario_dir: Path, monkeypatch, capsys) -> None:
    m = read_table(scenario_dir / M)
    code, out, err = run_check(scenario_dir, monkeypatch, capsys)
    assert code == 0, err
    assert m["rsrp_dbm"].isna().any()  # the tiny scenario has unreported beams, written as empty fields
    assert f"measurements.csv {len(m)}" in out


MORE_CASES: list[tuple[str, Callable[[Path], None], list[str]]] = [
    (
        "carrier-nan",
        yaml_edit(lambda d: d.update(frequencies_hz=[float("nan"), 3.5e9])),
        ["`frequencies_hz[0]` = nan must be a carrier in Hz"],
    ),
    (
        "carrier-inf",
        yaml_edit(lambda d: d.update(frequencies_hz=[2.1e9, float("inf")])),
        ["`frequencies_hz[1]` = inf must be a carrier in Hz"],
    ),
    (
        "round-number-huge",
        yaml_edit(lambda d: d["rounds"].update({2**70: d["rounds"].pop(2)})),
        ["`rounds` keys must be round numbers"],
    ),
    (
        "array-too-large",
        both_rounds(lambda df: df.assign(array_nh=1024, array_nv=1024)),
        ["`array_nh` = 1024 × `array_nv` is more than 4096 elements"],
    ),
]


@pytest.mark.parametrize(("mistake", "expected"), [(c[1], c[2]) for c in MORE_CASES], ids=[c[0] for c in MORE_CASES])
def test_more_malformed_scenarios(scenario_dir: Path, mistake, expected, monkeypatch, capsys) -> None:
    test_malformed_scenario_gives_one_line_and_exit_2(scenario_dir, mistake, expected, monkeypatch, capsys)


def test_trailing_empty_header_column_is_ignored(scenario_dir: Path, monkeypatch, capsys) -> None:
    text_edit(G, lambda t: "\n".join(line + "," for line in t.splitlines()) + "\n")(scenario_dir)
    code, out, err = run_check(scenario_dir, monkeypatch, capsys)
    assert code == 0, err
    assert "grids.csv: column(s) `Unnamed: 4` are not used" in " ".join(out.split())


def test_output_options_are_checked_before_any_work(scenario_dir: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    """A folder given where a file is written was a traceback after training (IsADirectoryError)."""
    for argv in (
        ["train", str(scenario_dir), "--model", "wnomp", "--out", str(tmp_path)],
        ["evaluate", str(tmp_path / "none.ckpt"), str(scenario_dir), "--json", str(tmp_path)],
        ["evaluate", str(tmp_path / "none.ckpt"), str(scenario_dir), "--report", str(scenario_dir / G)],
        ["predict", str(tmp_path / "none.ckpt"), str(scenario_dir), "--out", str(tmp_path)],
        [
            "predict",
            str(tmp_path / "none.ckpt"),
            str(scenario_dir),
            "--aps-cells",
            "11",
            "--aps-grids",
            "99999999999999999999999",
        ],
    ):
        monkeypatch.setattr(sys, "argv", ["rflscm", *argv])
        with pytest.raises(SystemExit) as exit_info:
            main()
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and len(err.strip().splitlines()) == 1, (argv, err)
        assert err.startswith("ConfigError: --"), err


def test_wnomp_outputs_hold_no_nan(scenario_dir: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    ckpt, pred, metrics = tmp_path / "w.ckpt", tmp_path / "p.csv", tmp_path / "m.json"
    for argv in (
        ["train", str(scenario_dir), "--model", "wnomp", "--out", str(ckpt), "--no-progress"],
        ["predict", str(ckpt), str(scenario_dir), "--out", str(pred)],
        ["evaluate", str(ckpt), str(scenario_dir), "--json", str(metrics)],
    ):
        monkeypatch.setattr(sys, "argv", ["rflscm", *argv])
        try:
            main()
        except SystemExit as exc:
            assert not exc.code, capsys.readouterr().err
    assert "NaN" not in metrics.read_text() and "Infinity" not in metrics.read_text()
    table = pd.read_csv(pred)
    assert len(table) and np.isfinite(table["rsrp_dbm"]).all()
