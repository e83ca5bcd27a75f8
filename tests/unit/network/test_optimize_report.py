"""The optimize report compares like with like and flags a recommendation whose checked gain is negative."""

from __future__ import annotations

import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from network_helpers import load, pencil_scenario

from rflscm.data import load_scenario
from rflscm.network.kpi import KPIConfig
from rflscm.network.optimize import objective_gain, verdict, write_round
from rflscm.network.report import kpi_table, verdict_markdown, write_report


def _kpis(coverage: float, sinr: float, rsrp: float = -95.0) -> dict:
    return {
        "coverage": coverage,
        "mean_sinr_db": sinr,
        "p5_sinr_db": sinr - 10,
        "overlap": 0.1,
        "mean_rsrp_dbm": rsrp,
        "no_signal": 0.0,
        "per_carrier": {},
    }


def _summary(objective: str, predicted: tuple, truth: tuple | None, held: tuple | None = None) -> dict:
    out = {"objective": objective, "predicted": {"before": _kpis(*predicted[0]), "after": _kpis(*predicted[1])}}
    if truth is not None:
        out["truth"] = {"before": _kpis(*truth[0]), "after": _kpis(*truth[1])}
    if held is not None:
        out["held_out"] = {"before": _kpis(*held[0]), "after": _kpis(*held[1])}
    return out


def test_a_negative_true_gain_is_flagged_even_when_the_prediction_gains() -> None:
    # the WNOMP case of the issue: predicted coverage +1.12 points, true −0.12 points
    s = _summary("coverage", ((0.974, 5.0), (0.9852, 5.0)), ((0.778, 0.1), (0.7768, 0.1)), ((0.9, 5), (0.95, 5)))
    v = verdict(s)
    assert v["flagged"] and v["basis"] == "true" and v["gain"] == pytest.approx(-0.0012)
    assert "-0.12 points" in v["text"] and "do not apply" in v["text"]
    line = verdict_markdown(v)
    assert "color:red" in line and "do not apply" in line


def test_without_truth_the_held_out_gain_decides() -> None:
    bad = verdict(_summary("sinr", ((0.9, 5.0), (0.9, 6.0)), None, ((0.9, 5.0), (0.9, 4.5))))
    assert bad["flagged"] and bad["basis"] == "held-out predicted" and "-0.50 dB" in bad["text"]
    good = verdict(_summary("sinr", ((0.9, 5.0), (0.9, 6.0)), None, ((0.9, 5.0), (0.9, 5.5))))
    assert not good["flagged"] and "color:red" not in verdict_markdown(good)
    # a true gain wins over the held-out one
    assert not verdict(_summary("coverage", ((0.9, 5), (0.95, 5)), ((0.7, 1), (0.71, 1)), ((0.9, 5), (0.8, 5))))[
        "flagged"
    ]
    assert objective_gain(_kpis(0.5, 0.0), _kpis(0.5, 10.0), "weighted") == pytest.approx(0.1)


def test_kpi_table_in_percent_and_db_with_held_out_column() -> None:
    s = _summary("coverage", ((0.974, 5.0), (0.991, 5.0)), ((0.778, 0.1), (0.796, 0.2)), ((0.9, 5), (0.95, 5)))
    result = SimpleNamespace(predicted=s["predicted"], truth=s["truth"], held_out=s["held_out"], held_out_grids=7)
    lines = kpi_table(result)
    assert "7 held-out grids" in lines[0] and "true gain" in lines[0]
    cov = next(line for line in lines if line.startswith("| coverage ratio (%)"))
    assert "| 97.40 | 99.10 | +1.70 | 77.80 | 79.60 | +1.80 | +5.00 |" in cov


def _result(scen, truth_after_cov: float) -> SimpleNamespace:
    """A hand-made optimisation result on the pencil scenario: the prediction gains, the truth as given."""
    cells = scen.cells[1]
    n_cells, n_grids = len(cells), len(scen.grid_ids())
    power = np.full((n_cells, n_grids), 1e-9)
    pred = {"before": _kpis(0.90, 5.0), "after": _kpis(0.95, 6.0)}
    truth = {"before": _kpis(0.80, 2.0, -99.0), "after": _kpis(truth_after_cov, 2.1, -99.5), "note": "test"}
    changes = pd.DataFrame(
        {
            "cell_id": [11],
            "site_id": [1],
            "freq_hz": [3.5e9],
            "ssb_codebook_before": ["pencil"],
            "ssb_codebook_after": ["pencil"],
            "elec_tilt_deg_before": [0.0],
            "elec_tilt_deg_after": [0.0],
            "mech_tilt_deg_before": [4.0],
            "mech_tilt_deg_after": [8.0],
            "azimuth_deg_before": [60.0],
            "azimuth_deg_after": [60.0],
        }
    )
    after = cells.copy()
    after.loc[after["cell_id"] == 11, "mech_tilt_deg"] = 8.0
    search = SimpleNamespace(
        method="coordinate-descent", evaluations=10, time_s=0.1, base_objective=0.9, objective=0.95
    )
    held = {"before": _kpis(0.9, 5.0), "after": _kpis(0.93, 5.5)}
    res = SimpleNamespace(
        model="wnomp",
        objective="coverage",
        search=search,
        cells_before=cells,
        cells_after=after,
        changes=changes,
        predicted=pred,
        power_before=power,
        power_after=power,
        known=None,
        truth=truth,
        truth_all=None,
        held_out=held,
        held_out_grids=3,
    )
    summary = {
        "kpi_pairs": "every (cell, grid) pair",
        "kpi_pair_count": n_cells * n_grids,
        "objective": "coverage",
        "predicted": pred,
        "truth": truth,
        "held_out": held,
        "level_gap": {k: pred["before"][k] - truth["before"][k] for k in ("coverage", "mean_sinr_db", "mean_rsrp_dbm")},
    }
    summary["verdict"] = verdict(summary)
    res.summary = lambda: summary
    return res


@pytest.mark.parametrize(("truth_after", "flagged"), [(0.79, True), (0.82, False)])
def test_report_flags_in_red_and_explains_the_gap(tmp_path: Path, truth_after: float, flagged: bool) -> None:
    scen = load(pencil_scenario(tmp_path / "pencil"))
    path = write_report(_result(scen, truth_after), scen, tmp_path / "out", KPIConfig(), 3, tmp_path / "out" / "s")
    text = path.read_text()
    assert ("color:red" in text) is flagged
    assert ("do not apply: the true coverage gain is -1.00 points" in text) is flagged
    assert "cover the same" in text and "+4.00 dB" in text  # the level gap: −95 dBm predicted vs −99 dBm true
    assert (tmp_path / "out" / "maps_3.5GHz.png").is_file() and (tmp_path / "out" / "maps_2.1GHz.png").is_file()


def test_the_what_if_round_names_files_relatively_and_moves_with_its_folder(tmp_path: Path) -> None:
    project = tmp_path / "project"
    scen = load(pencil_scenario(project / "scenario"))
    cells = scen.cells[1].copy()
    cells.loc[cells["cell_id"] == 11, "mech_tilt_deg"] = 8.0
    folder, rnd = write_round(scen, cells, project / "opt")
    text = (folder / "scenario.yaml").read_text()
    assert str(project) not in text and "../../scenario/" in text
    moved = tmp_path / "elsewhere" / "project2"
    moved.parent.mkdir()
    shutil.move(str(project), str(moved))
    again = load_scenario(moved / "opt" / "scenario")
    assert sorted(again.cells) == [1, 2, rnd] and again.fingerprint() == load_scenario(moved / "scenario").fingerprint()
    assert float(again.cells[rnd].set_index("cell_id").loc[11, "mech_tilt_deg"]) == 8.0


def test_without_truth_the_search_holds_grids_out_and_checks_on_them(tmp_path: Path) -> None:
    from network_helpers import single_bin_cache

    from rflscm.network.optimize import run_optimize
    from rflscm.network.space import build_space

    scen = load(pencil_scenario(tmp_path / "pencil"))
    cache = single_bin_cache(scen, -12.0, 30.0, 1e-15)
    space = build_space({}, scen.cells[1], scen.meta.codebooks)
    result = run_optimize(scen, cache, space, objective="sinr", verify=False, restarts=0, holdout_fraction=0.34)
    assert result.held_out_grids == 1 and result.truth is None
    s = result.summary()
    assert s["verdict"]["basis"] == "held-out predicted"
    assert s["verdict"]["gain"] == pytest.approx(s["held_out_gain"]["mean_sinr_db"])
    assert s["kpi_pair_count"] == len(scen.cell_ids()) * len(scen.grid_ids())  # predicted KPIs: every pair
