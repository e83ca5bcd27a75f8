"""`rflscm import` pieces: ARFCN conversion, (PCI, carrier) resolution, binning, the top-N rule, refusals."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import rflscm
from rflscm.data import load_scenario
from rflscm.data.geo import Origin, enu_to_geodetic
from rflscm.data.ingest import earfcn_to_hz, hz_to_nr_arfcn, import_raw, load_spec, nr_arfcn_to_hz
from rflscm.data.ingest.binning import bin_samples, keep_top_n
from rflscm.data.ingest.cellist import _cell_number
from rflscm.data.ingest.resolve import AMBIGUOUS, FAR_FROM_ID, NO_CELL, TOO_FAR, UNKNOWN_ID, resolve_cells
from rflscm.data.ingest.samples import Tally
from rflscm.data.ingest.spec import ImportSpec
from rflscm.data.pointcloud import PointCloud, write_point_cloud
from rflscm.errors import ConfigError, DataError

BOOKS = {
    "ssb4": {"type": "ssb", "azimuths_deg": [-30.0, 30.0], "tilts_deg": [0.0, 10.0]},
    "csi8": {"type": "dft", "n1": 8, "n2": 4, "o1": 1, "o2": 1, "beams_h": [-3, -1, 1, 3], "beams_v": [0, 1]},
}
ORIGIN = Origin(48.14, 11.57)


def _spec(**kw) -> ImportSpec:
    return ImportSpec(samples=("s.csv",), cells={0: "c.csv"}, codebooks=BOOKS, **kw)


def test_nr_arfcn_matches_3gpp_ts_38_104_table() -> None:
    # (N_REF, F_REF [MHz]) from the three ranges of TS 38.104 Table 5.4.2.1-1 and common band centres
    known = [
        (0, 0.0),
        (422000, 2110.0),
        (599999, 2999.995),
        (600000, 3000.0),
        (620000, 3300.0),
        (632628, 3489.42),
        (2016667, 24250.08),
        (2079167, 28000.08),
        (3279165, 99999.96),
    ]
    n = np.array([k for k, _ in known])
    np.testing.assert_allclose(nr_arfcn_to_hz(n), [f * 1e6 for _, f in known], rtol=0, atol=1e-3)
    np.testing.assert_array_equal(hz_to_nr_arfcn(nr_arfcn_to_hz(n)), n)
    assert np.isnan(nr_arfcn_to_hz(np.array([3279166, -1, 620000.5]))).all()


def test_earfcn_matches_3gpp_ts_36_101() -> None:
    n = np.array([300, 1300, 3100, 6300, 38000, 9999999])  # bands 1, 3, 7, 20, 38; none
    np.testing.assert_allclose(earfcn_to_hz(n)[:5], np.array([2140.0, 1815.0, 2655.0, 806.0, 2595.0]) * 1e6)
    assert np.isnan(earfcn_to_hz(n)[5])


def _cells() -> dict[int, pd.DataFrame]:
    # PCI 7 on 3.5 GHz twice (20 km apart), PCI 9 twice only 1.2 km apart, PCI 7 also on 2.1 GHz
    return {
        1: pd.DataFrame(
            {
                "cell_id": [1, 2, 3, 4, 5],
                "x": [0.0, 20_000.0, 5000.0, 5000.0, 0.0],
                "y": [0.0, 0.0, 0.0, 1200.0, 0.0],
                "pci": [7, 7, 9, 9, 7],
                "carrier_hz": [3.5e9, 3.5e9, 3.5e9, 3.5e9, 2.1e9],
            }
        )
    }


def _samples(rows: list[tuple[float, float, int, float]]) -> pd.DataFrame:
    x, y, pci, carrier = zip(*rows, strict=True)
    return pd.DataFrame({"x": x, "y": y, "round": 1, "pci": pci, "carrier_hz": carrier, "cell_name": ""})


def test_pci_resolution_nearest_far_ambiguous_and_unknown_are_counted() -> None:
    samples = _samples(
        [
            (100.0, 0.0, 7, 3.5e9),  # → cell 1 (cell 2 is 20 km away)
            (19_000.0, 0.0, 7, 3.5e9),  # → cell 2
            (100.0, 0.0, 7, 2.1e9 + 30e3),  # → cell 5 (carrier within 100 kHz)
            (5000.0, 500.0, 9, 3.5e9),  # 500 m and 700 m from two PCI-9 cells: ambiguous
            (5000.0, -3000.0, 9, 3.5e9),  # 3000 m vs 4200 m: 1.4× < 2×: ambiguous
            (5000.0, -200.0, 9, 3.5e9),  # 200 m vs 1400 m: 7×: cell 3
            (-11_000.0, 0.0, 7, 2.1e9),  # 11 km from the only candidate: too far
            (0.0, 0.0, 8, 3.5e9),  # no PCI 8
        ]
    )
    tally = Tally()
    out = resolve_cells(samples, _cells(), {}, _spec(), tally)
    assert out["cell_id"].tolist() == [1, 2, 5, 3]
    assert out["x"].tolist() == [100.0, 19_000.0, 100.0, 5000.0]
    assert tally.samples == {AMBIGUOUS: 2, TOO_FAR: 1, NO_CELL: 1}
    wider = Tally()
    assert len(resolve_cells(samples, _cells(), {}, _spec(max_distance_m=20_000.0), wider)) == 5
    assert TOO_FAR not in wider.samples


def _bin_input(values: dict[tuple[int, int], list[float]]) -> pd.DataFrame:
    rows = [
        {
            "round": 1,
            "cell_id": 1,
            "x": 10.0 * gx + 3.0,
            "y": 4.0,
            "z": 1.5,
            "beam_type": "ssb",
            "beam_id": b,
            "rsrp_dbm": v,
        }
        for (gx, b), vs in values.items()
        for v in vs
    ]
    return pd.DataFrame(rows)


def test_binning_linear_mean_count_spread_min_samples_and_outliers() -> None:
    df = _bin_input(
        {(0, 0): [-80.0, -90.0, -85.0], (0, 1): [-70.0, -71.0], (1, 0): [-80.0, -81.0, -80.0, -81.0, -80.0, -60.0]}
    )
    tally = Tally()
    bins = bin_samples(df, _spec(min_samples=3), tally).set_index(["ix", "beam_id"])
    mean = 10 * np.log10(np.mean(10 ** (np.array([-80.0, -90.0, -85.0]) / 10)))
    assert bins.loc[(0, 0), "rsrp_dbm"] == pytest.approx(mean)  # linear mean, not the dB mean −85
    assert bins.loc[(0, 0), "samples"] == 3
    assert bins.loc[(0, 0), "std_db"] == pytest.approx(np.std([-80.0, -90.0, -85.0], ddof=1))
    assert (0, 1) not in bins.index  # two samples < min_samples 3
    assert bins.loc[(1, 0), "samples"] == 5  # −60 is 20 dB from the median, MAD 0.5 dB: an outlier
    assert bins.loc[(1, 0), "rsrp_dbm"] < -79.0
    assert list(tally.samples.values()) == [1, 2] and list(tally.bins.values()) == [0, 1]
    kept_all = bin_samples(df, _spec(min_samples=1, outlier_k=0.0), Tally()).set_index(["ix", "beam_id"])
    assert kept_all.loc[(1, 0), "samples"] == 6 and (0, 1) in kept_all.index


def test_top_n_keeps_the_strongest_beams_of_each_report() -> None:
    df = _bin_input({(0, b): [-70.0 - b] for b in range(5)})
    df = pd.concat([df, df.assign(beam_type="csi")], ignore_index=True)
    bins = bin_samples(df, _spec(min_samples=1), Tally())
    tally = Tally()
    kept = keep_top_n(bins, "csi", 2, tally)
    assert sorted(kept[kept["beam_type"] == "csi"]["beam_id"]) == [0, 1]
    assert (kept["beam_type"] == "ssb").sum() == 5
    assert list(tally.bins.values()) == [3]


def _write_raw(tmp: Path, samples: pd.DataFrame, antenna: str = "tr38901") -> Path:
    # the headers of the planning-tool export; the codebooks come from `cell_defaults`
    cells = pd.DataFrame(
        {
            "Cell": ["A1", "A2"],
            "PCI": [11, 12],
            "EARFCN": [1300, 1300],
            "Latitude": [48.14, 48.14],
            "Longitude": [11.57, 11.57],
            "Height_AGL_m": [25.0, 25.0],
            "Azimuth": [0.0, 180.0],
            "M_Tilt": [2.0, 2.0],
            "E_Tilt": [4.0, 4.0],
            "Antenna": antenna,
        }
    )
    cells.to_csv(tmp / "cells.csv", index=False)
    samples.to_csv(tmp / "samples.csv", index=False)
    spec = tmp / "import.yaml"
    spec.write_text(
        f"samples: samples.csv\ncells: cells.csv\ncodebooks: {BOOKS}\n"
        "cell_defaults: {ssb_codebook: ssb4, csi_codebook: csi8}\n"
    )
    return spec


def _raw_samples(n: int = 4) -> pd.DataFrame:
    xyz = np.array([[15.0, 25.0, 1.5]] * n) + np.linspace(0, 3, n)[:, None] * [1, 1, 0]
    lat, lon, _ = enu_to_geodetic(xyz, ORIGIN)
    return pd.DataFrame(
        {
            "timestamp": [f"2024-05-01T08:00:{i:02d}" for i in range(n)],
            "lat": lat,
            "lon": lon,
            "PCI": 11,
            "freq": 1815.0,
            "ssb_index": 2,
            "rsrp_dbm": -100.0 - np.arange(n),
        }
    )


def test_import_of_planning_tool_columns_makes_a_checked_scenario(tmp_path: Path) -> None:
    spec = load_spec(
        _write_raw(tmp_path, _raw_samples()),
        {"columns": {"freq_mhz": "freq"}, "beam_type": "ssb", "origin": {"lat": 48.14, "lon": 11.57}},
    )
    res = import_raw(spec, tmp_path / "sc")
    sc = load_scenario(tmp_path / "sc")
    assert sc.meta.origin == ORIGIN and res.samples_kept == 4 and res.dropped.dropped == 0
    m = sc.measurements
    assert len(m) == 1 and m["cell_id"].iloc[0] == 0 and m["beam_id"].iloc[0] == 2  # A1 → 0
    assert m["rsrp_dbm"].iloc[0] == pytest.approx(10 * np.log10(np.mean(10 ** ((-100.0 - np.arange(4)) / 10))))
    assert sc.grids[["x", "y"]].to_numpy().tolist() == [[15.0, 25.0]]
    np.testing.assert_allclose(sc.cells[1][["x", "y", "z"]].to_numpy(), [[0, 0, 25.0]] * 2, atol=1e-6)
    assert sc.meta.rsrp_threshold_dbm == -120.0 and sc.cells[1]["freq_hz"].tolist() == [1815e6, 1815e6]
    assert sc.cells[1]["elec_tilt_deg"].tolist() == [4.0, 4.0] and sc.cells[1]["azimuth_deg"].tolist() == [0.0, 180.0]


def test_import_refusals_name_file_row_and_value(tmp_path: Path) -> None:
    over = {"columns": {"freq_mhz": "freq"}, "beam_type": "ssb"}
    bad = _raw_samples().assign(rsrp_dbm=[-100.0, 0.02, -100.0, -100.0])
    with pytest.raises(DataError, match=r"samples.csv row 2 \(line 3\): `rsrp_dbm` = 0.02 is outside"):
        import_raw(load_spec(_write_raw(tmp_path, bad), dict(over)), tmp_path / "a")
    beyond = _raw_samples().assign(ssb_index=[2, 2, 9, 2])
    with pytest.raises(DataError, match=r"samples.csv row 3: `beam_id` = 9 is beyond the ssb codebook of cell 0"):
        import_raw(load_spec(_write_raw(tmp_path, beyond), dict(over)), tmp_path / "b")
    with pytest.raises(DataError, match=r"cells.csv row 1 \(line 2\): `element` = 'AAU5613' names no pattern file"):
        import_raw(load_spec(_write_raw(tmp_path, _raw_samples(), antenna="AAU5613"), dict(over)), tmp_path / "d")
    msi = "sample_65deg_3500MHz.msi"  # the 3.5 GHz pattern on 1815 MHz (EARFCN 1300) cells
    shutil.copyfile(Path(rflscm.__file__).parent / "assets" / "antennas" / msi, tmp_path / msi)
    with pytest.raises(
        DataError,
        match=r"^cells.csv row 1 \(line 2\): `element` = '.*3500MHz.msi' is measured at 3500 MHz, but this cell's "
        r"carrier is 1815 MHz \(beyond ±10 %\); give the pattern of this band. 1 more row",
    ):
        import_raw(load_spec(_write_raw(tmp_path, _raw_samples(), antenna=msi), dict(over)), tmp_path / "e")
    report = _raw_samples().assign(timestamp="2024-05-01T08:00:00", ssb_index=[0, 1, 2, 3])
    rule = {**over, "reporting": {"ssb": {"rule": "top_n", "top_n": 3}}, "min_samples": 1}
    with pytest.raises(
        DataError,
        match=r"row 1: `time` = '2024-05-01T08:00:00' holds a ssb report .* 4 beams, more "
        r"than the declared `reporting.ssb.top_n` = 3",
    ):
        import_raw(load_spec(_write_raw(tmp_path, report), dict(rule)), tmp_path / "c")


def test_weak_bins_set_the_threshold_or_are_dropped_and_counted(tmp_path: Path) -> None:
    weak = _raw_samples().assign(rsrp_dbm=-130.0)
    over = {"columns": {"freq_mhz": "freq"}, "beam_type": "ssb"}
    res = import_raw(load_spec(_write_raw(tmp_path, weak), dict(over)), tmp_path / "a")
    assert res.threshold_dbm == -130.0 and load_scenario(tmp_path / "a").meta.rsrp_threshold_dbm == -130.0
    with pytest.raises(DataError, match="no bin kept"):
        import_raw(load_spec(_write_raw(tmp_path, weak), {**over, "rsrp_threshold_dbm": -120.0}), tmp_path / "b")


def test_rounds_from_time_ranges_and_outside_counted(tmp_path: Path) -> None:
    samples = pd.concat(
        [
            _raw_samples(),
            _raw_samples().assign(timestamp="2024-05-02T09:00:00", rsrp_dbm=-90.0),
            _raw_samples().assign(timestamp="2024-06-01T00:00:00"),
        ],
        ignore_index=True,
    )
    times = {1: ("2024-05-01", "2024-05-02"), 2: ("2024-05-02", "2024-05-03")}
    over = {"columns": {"freq_mhz": "freq"}, "beam_type": "ssb", "round_times": times}
    res = import_raw(load_spec(_write_raw(tmp_path, samples), over), tmp_path / "sc")
    m = load_scenario(tmp_path / "sc").measurements.set_index("round")["rsrp_dbm"]
    assert res.rounds == [1, 2] and m.loc[2] == pytest.approx(-90.0) and m.loc[1] < -100.0
    assert list(res.dropped.samples.values()) == [4] and "outside every round" in next(iter(res.dropped.samples))


def test_cli_refusal_is_one_line_and_exit_2(tmp_path: Path, monkeypatch, capsys) -> None:
    import sys

    from rflscm.cli import main

    spec = _write_raw(tmp_path, _raw_samples())  # `freq` is not mapped: ambiguous, so the carrier is missing
    monkeypatch.setattr(
        sys, "argv", ["rflscm", "import", str(spec), "--out", str(tmp_path / "sc"), "--beam-type", "ssb"]
    )
    with pytest.raises(SystemExit) as exit_info:
        main()
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.count("\n") == 1
    assert "samples.csv: gives pci but no carrier; add freq_hz, freq_mhz, nr_arfcn or earfcn" in err
    assert not (tmp_path / "sc").exists()


def test_one_cell_file_per_round_and_a_round_column_give_the_same_scenario(tmp_path: Path) -> None:
    spec = _write_raw(tmp_path, _raw_samples())
    cells = pd.read_csv(tmp_path / "cells.csv")
    cells.to_csv(tmp_path / "r1.csv", index=False)
    cells.assign(Azimuth=[10.0, 190.0]).to_csv(tmp_path / "r2.csv", index=False)
    pd.concat([cells.assign(round=1), cells.assign(round=2, Azimuth=[10.0, 190.0])]).to_csv(
        tmp_path / "all.csv", index=False
    )
    samples = pd.concat([_raw_samples().assign(round=1), _raw_samples().assign(round=2)], ignore_index=True)
    samples.to_csv(tmp_path / "samples.csv", index=False)
    over = {"columns": {"freq_mhz": "freq"}, "beam_type": "ssb"}
    import_raw(load_spec(spec, {**over, "cells": [str(tmp_path / "r1.csv"), str(tmp_path / "r2.csv")]}), tmp_path / "a")
    import_raw(load_spec(spec, {**over, "cells": [str(tmp_path / "all.csv")]}), tmp_path / "b")
    a, b = load_scenario(tmp_path / "a"), load_scenario(tmp_path / "b")
    assert a.cells[2]["azimuth_deg"].tolist() == b.cells[2]["azimuth_deg"].tolist() == [10.0, 190.0]
    assert a.measurements.equals(b.measurements) and a.rounds() == [1, 2]
    bad = pd.concat([cells.assign(round=1), cells.assign(round=2, PCI=[11, "x"])])
    bad.to_csv(tmp_path / "bad.csv", index=False)
    with pytest.raises(DataError, match=r"bad.csv row 4 \(line 5\): `pci` = 'x' is not a number"):
        import_raw(load_spec(spec, {**over, "cells": [str(tmp_path / "bad.csv")]}), tmp_path / "c")


def test_cell_id_samples_unknown_or_far_from_their_cell_are_counted() -> None:
    samples = _samples([(10.0, 0.0, -1, np.nan), (0.0, 50_000.0, -1, np.nan), (0.0, 0.0, -1, np.nan)])
    samples["cell_name"] = ["A", "A", "Z"]
    tally = Tally()
    out = resolve_cells(samples, _cells(), {"A": 1}, _spec(), tally)
    assert out["cell_id"].tolist() == [1] and out["x"].tolist() == [10.0]
    assert tally.samples == {UNKNOWN_ID: 1, FAR_FROM_ID: 1}


def _cloud(shift: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> PointCloud:
    # ground over ±60 m (class 2) and one 20 m block (class 6), in the import's frame, moved by `shift`
    g = np.stack(np.meshgrid(np.arange(-60.0, 61.0, 4.0), np.arange(-60.0, 61.0, 4.0)), -1).reshape(-1, 2)
    ground = np.column_stack([g, np.zeros(len(g))])
    block = np.stack(np.meshgrid(np.arange(30.0, 41.0, 2.0), np.arange(30.0, 41.0, 2.0), [20.0]), -1).reshape(-1, 3)
    xyz = np.concatenate([ground, block]) + np.asarray(shift)
    return PointCloud(xyz, np.r_[np.full(len(ground), 2), np.full(len(block), 6)])


def test_point_cloud_is_copied_in_and_must_be_in_the_import_frame(tmp_path: Path) -> None:
    over = {"columns": {"freq_mhz": "freq"}, "beam_type": "ssb", "origin": {"lat": 48.14, "lon": 11.57}}
    spec = _write_raw(tmp_path, _raw_samples())
    for name, shift in (("ok.laz", (0.0, 0.0, 0.0)), ("utm.ply", (3000.0, 0.0, 0.0)), ("msl.npy", (0, 0, 519.0))):
        write_point_cloud(_cloud(shift), tmp_path / name)
    res = import_raw(load_spec(spec, {**over, "point_cloud": str(tmp_path / "ok.laz")}), tmp_path / "a")
    sc = load_scenario(tmp_path / "a")
    assert sc.meta.point_cloud == "point_cloud.laz" and res.point_cloud_points == len(_cloud().xyz)
    assert sc.point_cloud is not None and sc.point_cloud.class_counts() == _cloud().class_counts()
    with pytest.raises(DataError, match=r"^utm.ply: covers x 2940…3060 m, .* does not overlap the imported grids"):
        import_raw(load_spec(spec, {**over, "point_cloud": str(tmp_path / "utm.ply")}), tmp_path / "b")
    with pytest.raises(DataError, match=r"^msl.npy: its ground over the grids .* z = 519.0 m, 517.5 m above"):
        import_raw(load_spec(spec, {**over, "point_cloud": str(tmp_path / "msl.npy")}), tmp_path / "c")
    write_point_cloud(_cloud((690_000.0, 5_334_000.0, 0.0)), tmp_path / "utm33.laz")  # a UTM export, not shifted
    with pytest.raises(DataError, match=r"^utm33.laz point 1: .* implausible .* needs the cloud in its local frame"):
        import_raw(load_spec(spec, {**over, "point_cloud": str(tmp_path / "utm33.laz")}), tmp_path / "e")
    (tmp_path / "cloud.txt").write_text("1 2 3\n")
    with pytest.raises(DataError, match=r"cloud.txt: unsupported point cloud format '.txt'"):
        import_raw(load_spec(spec, {**over, "point_cloud": str(tmp_path / "cloud.txt")}), tmp_path / "d")
    assert not any((tmp_path / d).exists() for d in "bcd")


def test_cli_refuses_a_cloud_outside_the_grids_in_one_line(tmp_path: Path, monkeypatch, capsys) -> None:
    import sys

    from rflscm.cli import main

    spec = _write_raw(tmp_path, _raw_samples())
    write_point_cloud(_cloud((0.0, -5000.0, 0.0)), tmp_path / "far.ply")
    argv = [
        "rflscm",
        "import",
        str(spec),
        "--out",
        str(tmp_path / "sc"),
        "--beam-type",
        "ssb",
        "--col",
        "freq_mhz=freq",
    ]
    monkeypatch.setattr(sys, "argv", [*argv, "--point-cloud", str(tmp_path / "far.ply")])
    with pytest.raises(SystemExit) as exit_info:
        main()
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.count("\n") == 1, err
    assert "far.ply: covers" in err and "does not overlap the imported grids" in err and "local frame" in err
    assert not (tmp_path / "sc").exists()
    monkeypatch.setattr(sys, "argv", argv)  # no cloud: imported, and told how to train RF-LSCM without one
    main()
    out = " ".join(capsys.readouterr().out.split())
    assert "no point cloud" in out and "--set prior.enabled=false" in out


def test_per_table_column_maps_unix_times_and_a_cell_list_without_pci(tmp_path: Path) -> None:
    # the samples name their cell `Serving` (a name), the cell list `Cell`; a shared `lat` map for the samples
    # only must not hide the cell list's own `Latitude`; times are Unix seconds; the cell list has no PCI
    samples = _raw_samples().rename(columns={"lat": "GPS Lat"}).drop(columns=["PCI", "freq"])
    samples = samples.assign(Serving="A1", timestamp=1714550400 + np.arange(4))
    spec = _write_raw(tmp_path, samples)
    pd.read_csv(tmp_path / "cells.csv").drop(columns="PCI").to_csv(tmp_path / "cells.csv", index=False)
    over = {
        "beam_type": "ssb",
        "min_samples": 1,
        "columns": {"lat": "GPS Lat", "samples": {"cell_id": "Serving"}},
        "round_times": {1: ("2024-05-01T08:00:00Z", "2024-05-01T08:00:02Z"), 2: ("2024-05-01T08:00:02Z", "2024-06-01")},
    }
    res = import_raw(load_spec(spec, over), tmp_path / "a")
    m = load_scenario(tmp_path / "a").measurements
    assert res.rounds == [1, 2] and m.groupby("round").size().to_dict() == {1: 1, 2: 1}
    assert (m["cell_id"] == 0).all() and res.samples_kept == 4
    by_pci = _raw_samples()  # PCI + carrier samples cannot be matched to a list without PCI: one line
    by_pci.to_csv(tmp_path / "samples.csv", index=False)
    with pytest.raises(DataError, match=r"samples.csv row 1: names its cell by `pci` = 11, but the cell list has no"):
        import_raw(load_spec(spec, {"beam_type": "ssb", "columns": {"freq_mhz": "freq"}}), tmp_path / "b")
    with pytest.raises(ConfigError, match=r"import: `columns`.samples: unknown rflscm column name 'azimuth_deg'"):
        load_spec(spec, {"columns": {"samples": {"azimuth_deg": "Az"}}})


def test_no_bin_kept_names_every_reason_and_names_keep_their_numbers(tmp_path: Path) -> None:
    samples = _raw_samples().assign(timestamp="2024-05-09T00:00:00Z")
    over = {"columns": {"freq_mhz": "freq"}, "beam_type": "ssb", "round_times": {1: ("2024-05-01", "2024-05-02")}}
    with pytest.raises(
        DataError, match=r"^import: no bin kept; all 4 samples were dropped \(samples.csv: time outside every round"
    ):
        import_raw(load_spec(_write_raw(tmp_path, samples), over), tmp_path / "a")
    ids: dict[str, int] = {}
    got = [ids.setdefault(n, _cell_number(n, ids)) for n in ["7", "A", "007", "8", "B", "7"]]
    assert got == [7, 8, 9, 10, 11, 7]  # numbers kept while free; a name never shares a number with another


def test_col_flags_map_one_table_over_the_columns_file(tmp_path: Path) -> None:
    from rflscm.cli.import_ import _column_file, _column_flags

    (tmp_path / "map.yaml").write_text("columns: {lat: Latitude, cells: {cell_id: Cell}}\n")
    base = _column_file(tmp_path / "map.yaml")
    got = _column_flags(base, {"samples.cell_id": "Serving", "cells.pci": "PCI", "lon": "Lng"})
    assert got == {
        "lat": "Latitude",
        "cells": {"cell_id": "Cell", "pci": "PCI"},
        "samples": {"cell_id": "Serving"},
        "lon": "Lng",
    }
    (tmp_path / "bad.yaml").write_text("lat: [1, 2]\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: `lat` must be the name of your column \(text\)"):
        _column_file(tmp_path / "bad.yaml")


def test_terrain_puts_cells_and_samples_above_the_ground(tmp_path: Path) -> None:
    # a slope z = 500 + 0.1·x [m] as an XYZ table in the import frame; the origin at 500 m
    u = np.arange(-100.0, 101.0, 20.0)
    xx, yy = np.meshgrid(u, u)
    pd.DataFrame({"x": xx.ravel(), "y": yy.ravel(), "z": 500.0 + 0.1 * xx.ravel()}).to_csv(
        tmp_path / "dem.csv", index=False
    )
    samples = pd.concat([_raw_samples(), _raw_samples().assign(lat=48.2)], ignore_index=True)  # the second 6.7 km off
    spec = _write_raw(tmp_path, samples)
    over = {
        "columns": {"freq_mhz": "freq"},
        "beam_type": "ssb",
        "origin": {"lat": 48.14, "lon": 11.57, "height_m": 500.0},
        "terrain": str(tmp_path / "dem.csv"),
    }
    res = import_raw(load_spec(spec, over), tmp_path / "a")
    sc = load_scenario(tmp_path / "a")
    assert sc.meta.terrain == "terrain.csv" and res.dropped.samples == {
        "dem.csv: outside the terrain (or on a nodata cell)": 4
    }
    np.testing.assert_allclose(sc.cells[1]["z"], [25.0, 25.0], atol=1e-6)  # at x = 0 the ground is the origin's 500 m
    g = sc.grids.iloc[0]
    assert g["z"] == pytest.approx(1.5 + 0.1 * (g["x"] + 1.5), abs=0.01)  # UEs 1.5 m above the slope at x 15…18
    cells = pd.read_csv(tmp_path / "cells.csv").assign(Latitude=[48.14, 48.16])
    cells.to_csv(tmp_path / "cells.csv", index=False)
    with pytest.raises(DataError, match=r"^cells.csv: cell 'A2' at x = .* lies outside the terrain 'dem.csv'"):
        import_raw(load_spec(spec, over), tmp_path / "b")


def test_headers_with_units_in_brackets_match_only_in_rflscm_units() -> None:
    from rflscm.data.ingest.spec import canonical

    cols = ["Latitude (deg)", "Longitude (WGS84)", "RSRP [dBm]", "Freq (MHz)", "SSB Index", "Height (ft)", "Time (UTC)"]
    got = list(canonical(pd.DataFrame(columns=cols), _spec(), "samples").columns)
    assert got == ["lat", "lon", "rsrp_dbm", "freq_mhz", "beam_id", "Height (ft)", "time"]  # feet stay unread
    cols = ["Cell Name", "Azimuth (deg)", "Mech. Tilt (deg)", "E-Tilt (°)", "Lat [°]", "Height AGL (m)", "Height (cm)"]
    got = list(canonical(pd.DataFrame(columns=cols), _spec(), "cells").columns)
    assert got == ["cell_id", "azimuth_deg", "mech_tilt_deg", "elec_tilt_deg", "lat", "height_m", "Height (cm)"]
