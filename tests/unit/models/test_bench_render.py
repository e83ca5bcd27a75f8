"""The render bench (:mod:`rflscm.bench.render_speed`): its worker, run by path, answers what the model answers in
process; its patterns, comparison and summary."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from tiny_rflscm import tiny_config


def test_render_worker_answers_what_the_model_answers(tmp_path) -> None:
    from rflscm.bench.render_speed import _compare, _grad_reference, _patterns, _summary, _worker
    from rflscm.data import load_scenario
    from rflscm.data.examples import tiny_scenario
    from rflscm.geometry import AngleGrid
    from rflscm.models.rflscm import RFLSCM
    from rflscm.train import fit

    scenario = load_scenario(tiny_scenario(tmp_path / "tiny", seed=0))
    model = RFLSCM.build(tiny_config(), AngleGrid.full_sphere(10, 12))
    fit(model, scenario, progress=False)
    ckpt = model.save(tmp_path / "m.ckpt")
    patterns = _patterns(scenario, "quick")
    by_cell = patterns["by_cell_cells"]
    assert len(np.unique(by_cell)) == min(4, len(scenario.cell_ids())) and len(patterns["mixed_cells"]) == 512
    np.savez(tmp_path / "pairs.npz", **patterns)
    src = Path(__import__("rflscm").__file__).resolve().parents[1]
    row = _worker(src, ckpt, tmp_path / "pairs.npz", tmp_path / "aps.pt", threads=1, profile=True)
    assert row["by_cell"]["pairs"] == len(by_cell) and row["mixed"]["cpu_s"] > 0 and row["peak_rss_mb"] > 0
    assert row["by_cell"]["minor_faults"] >= 0 and row["profile"]["top"][0]["cum_s"] > 0
    assert row["by_cell"]["decoder_evals"]["coarse"] > 0 and row["by_cell"]["decoder_evals"]["fine"] > 0
    aps = torch.load(tmp_path / "aps.pt", weights_only=True)
    model.corrections.rendered = None  # the worker times the renderer, not the pass's kept renders
    for name in ("by_cell", "mixed"):
        here = model.aps(patterns[f"{name}_cells"], patterns[f"{name}_grids"], patterns[f"{name}_xyz"])
        assert _compare(aps[name], here) == {"equal": True, "max_rel_diff": 0.0}
    assert _compare(aps["mixed"] * 1.5, aps["mixed"])["max_rel_diff"] > 0.4
    assert _grad_reference(model, patterns)["equal"]
    summary = _summary([row, row], ["by_cell", "mixed"])
    assert summary["by_cell"]["pairs_per_cpu_s"] == len(by_cell) / row["by_cell"]["cpu_s"]


def test_render_baseline_must_hold_an_exported_src(tmp_path) -> None:
    import pytest

    from rflscm.bench.b09_time_to_target import baseline_src
    from rflscm.bench.render_speed import BASELINE
    from rflscm.errors import ConfigError

    with pytest.raises(ConfigError, match=f"render: --baseline .* `git archive {BASELINE} src"):
        baseline_src(tmp_path, "render", BASELINE)
    (tmp_path / "src" / "rflscm").mkdir(parents=True)
    (tmp_path / "src" / "rflscm" / "__init__.py").write_text("")
    assert baseline_src(tmp_path, "render", BASELINE) == (tmp_path / "src").resolve()
