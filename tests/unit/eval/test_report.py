"""The report: Markdown with the metric table, linked PNG figures that exist and are not empty."""

from __future__ import annotations

import re

from eval_helpers import GRID
from matplotlib.image import imread

from rflscm.eval import fit_with_protocol, run_evaluation
from rflscm.eval.report import metric_rows, write_report
from rflscm.models import MODEL_REGISTRY


def test_report_links_readable_figures(sim_scenario, tmp_path) -> None:
    model = MODEL_REGISTRY["wnomp"].build(None, GRID, "cpu")
    fit_with_protocol(model, sim_scenario, None, progress=False)
    evaluation = run_evaluation(model, sim_scenario)
    path = write_report(evaluation, sim_scenario, model, tmp_path / "report")
    text = path.read_text()
    links = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text)
    carriers = {f"network_{f / 1e9:g}GHz.png" for f in sim_scenario.meta.frequencies_hz}
    assert set(links) == {"coverage.png", "error_cdf.png", "errors.png", "per_cell.png", "aps.png", *carriers}
    for name in links:
        image = imread(tmp_path / "report" / name)
        assert image.shape[0] > 300 and image.shape[1] > 600
        assert image[..., :3].std() > 0.05  # not a blank canvas
    rows = metric_rows(evaluation.metrics)
    assert rows[0][0] == "MAE SSB, all cells [dB]"
    assert f"| {rows[0][0]} | {rows[0][1]} |" in text
    assert "changed cells" in text and (tmp_path / "report" / "metrics.json").is_file()
    # the per-cell table says how many pairs each MAE rests on; the APS reference is named, not scored 0
    header = next(line for line in text.splitlines() if line.startswith("| cell |"))
    assert "SSB pairs" in header and "CSI pairs" in header
    assert "0 (reference)" not in text and "an all-zero APS scores 0 dB" in text
    # the network maps and their KPIs, measured and predicted on the same pairs
    assert "| coverage, RSRP ≥ -105 dBm (%) |" in text and "same" in text


def test_pair_counts_and_few_pair_marks(sim_scenario) -> None:
    from rflscm.eval.report import _pair_counts, _per_cell_table

    model = MODEL_REGISTRY["wnomp"].build(None, GRID, "cpu")
    fit_with_protocol(model, sim_scenario, None, progress=False)
    evaluation = run_evaluation(model, sim_scenario)
    counts = _pair_counts(evaluation)
    res = evaluation.beams["ssb"]
    cell = int(res.pairs["cell_id"].to_numpy()[res.rows()][0])
    assert counts[str(cell)]["ssb"] == int((res.pairs["cell_id"].to_numpy()[res.rows()] == cell).sum())
    per_cell = {
        "511": {
            "changed": True,
            "ssb": 14.65,
            "csi": None,
            "oracle": {"ssb": 1.0, "csi": None},
            "trivial": {"ssb": 3.0, "csi": None},
        }
    }
    table = _per_cell_table(per_cell, {"511": {"ssb": 1}})
    assert "| 511 | yes | 1 ⚠ | 14.65 |" in table
