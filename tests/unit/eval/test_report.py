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
    assert set(links) == {"coverage.png", "errors.png", "per_cell.png", "aps.png"}
    for name in links:
        image = imread(tmp_path / "report" / name)
        assert image.shape[0] > 300 and image.shape[1] > 600
        assert image[..., :3].std() > 0.05  # not a blank canvas
    rows = metric_rows(evaluation.metrics)
    assert rows[0][0] == "MAE SSB, all cells [dB]"
    assert f"| {rows[0][0]} | {rows[0][1]} |" in text
    assert "changed cells" in text and (tmp_path / "report" / "metrics.json").is_file()
