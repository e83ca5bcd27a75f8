"""The demo's comparison table is saved beside its reports (Markdown, CSV, JSON), not only printed."""

from __future__ import annotations

import csv
import json

from rflscm.cli.demo import save_comparison


def _metrics(mae: float, train_s: float) -> dict:
    block = {"ssb": {"all": mae, "changed": mae + 1}, "csi": {"all": mae + 2, "changed": None}}
    return {
        "mae_db": block,
        "oracle_mae_db": block,
        "trivial_mae_db": block,
        "noise_floor_mae_db": block,
        "bias_db": {"ssb": {"all": -0.5}, "csi": {"all": 0.25}},
        "model": {"fit": {"train_time_s": train_s}},
    }


def test_comparison_is_saved_in_three_formats(tmp_path) -> None:
    results = {"wnomp": _metrics(3.0, 12.0), "rflscm": _metrics(2.5, 170.0)}
    paths = save_comparison(results, "Antenna adjustment", tmp_path)
    assert [p.name for p in paths] == ["comparison.md", "comparison.csv", "comparison.json"]
    md = paths[0].read_text()
    assert "| metric | wnomp | rflscm | model floor | noise floor | trivial |" in md
    assert "| SSB MAE, all cells (dB) | 3.00 | 2.50 | 3.00 | 3.00 | 3.00 |" in md
    assert "| CSI-RS MAE, changed cells (dB) | — | — |" in md
    rows = list(csv.reader(paths[1].open()))
    assert rows[0][:3] == ["metric", "wnomp", "rflscm"] and rows[-1][:3] == ["training time (s)", "12", "170"]
    data = json.loads(paths[2].read_text())
    assert data["title"] == "Antenna adjustment" and data["rows"][0][2] == "2.50"


def _with_unseen(mae: float, seen_mae: float, answers_unseen: bool) -> dict:
    metrics = _metrics(mae, 10.0)
    seen = _metrics(seen_mae, 10.0)
    metrics["seen"] = {k: seen[k] for k in ("mae_db", "oracle_mae_db", "trivial_mae_db", "noise_floor_mae_db")}
    metrics["seen"]["bias_db"] = {"ssb": {"all": -0.1}, "csi": {"all": 0.1}}
    metrics["seen"]["pairs"] = {"ssb": 90, "csi": 80}
    unseen_mae = {"ssb": 6.0, "csi": 7.0}
    metrics["unseen"] = {
        "mae_db": unseen_mae if answers_unseen else {"ssb": None, "csi": None},
        "oracle_mae_db": {"ssb": 2.0, "csi": 2.5},
        "noise_floor_mae_db": {"ssb": 1.5, "csi": 1.5},
        "trivial_mae_db": {"ssb": 9.0, "csi": 9.5},
        "pairs": {"ssb": 10, "csi": 20},
    }
    metrics["model"]["supports_unseen_grids"] = answers_unseen
    return metrics


def test_comparison_scores_both_models_on_the_same_pairs(tmp_path) -> None:
    """WNOMP scores only grids with a round-1 report; RF-LSCM's all-pairs MAE also holds the others.  The table
    compares both on the pairs with reports and gives the others their own rows."""
    results = {"wnomp": _with_unseen(3.0, 3.0, False), "rflscm": _with_unseen(3.4, 2.9, True)}
    md = save_comparison(results, "Antenna adjustment", tmp_path)[0].read_text()
    assert "| SSB MAE, all cells, grids with round-1 reports (dB) | 3.00 | 2.90 | 3.00 | 3.00 | 3.00 |" in md
    assert "| SSB MAE, grids without round-1 reports, 10 pairs (dB) | — | 6.00 | 2.00 | 1.50 | 9.00 |" in md
    assert "| CSI-RS mean signed error, grids with round-1 reports (dB) | 0.10 | 0.10 |" in md
    assert "3.40" not in md
    results["wnomp"]["unseen"]["pairs"]["csi"] = 0  # no CSI-RS pair without a report: no row for it
    md = save_comparison(results, "Antenna adjustment", tmp_path)[0].read_text()
    assert "SSB MAE, grids without round-1 reports" in md and "CSI-RS MAE, grids without" not in md


def test_comparison_of_models_alike_keeps_every_pair(tmp_path) -> None:
    results = {"a": _with_unseen(3.4, 2.9, True), "b": _with_unseen(3.2, 3.0, True)}
    md = save_comparison(results, "t", tmp_path)[0].read_text()
    assert "| SSB MAE, all cells (dB) | 3.40 | 3.20 |" in md and "without round-1" not in md
