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
