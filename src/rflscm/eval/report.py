"""The evaluation report: ``report.md`` with the metric table and PNG figures (SPEC §1.4, §5)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from rflscm.eval import plots
from rflscm.eval.evaluate import BeamResult, Evaluation

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario

APS_EXAMPLES = 3


def _fmt(value: float | None, unit: str = "") -> str:
    return "–" if value is None else f"{value:.2f}{unit}"


def metric_rows(metrics: dict[str, Any]) -> list[tuple[str, str, str, str]]:
    """``(metric, model, oracle, trivial)`` rows of the summary table, as text."""
    rows = []
    for beam_type in ("ssb", "csi"):
        for subset in ("all", "changed"):
            if subset == "changed" and metrics["mae_db"][beam_type]["changed"] is None:
                continue
            rows.append((
                f"MAE {beam_type.upper()}, {subset} cells [dB]",
                _fmt(metrics["mae_db"][beam_type][subset]),
                _fmt(metrics["oracle_mae_db"][beam_type][subset]),
                _fmt(metrics["trivial_mae_db"][beam_type][subset]),
            ))  # fmt: skip
    unseen = metrics["unseen"]
    for beam_type in ("ssb", "csi"):
        if unseen["pairs"][beam_type]:
            rows.append((
                f"MAE {beam_type.upper()}, unseen pairs [dB] (n={unseen['pairs'][beam_type]})",
                _fmt(unseen["mae_db"][beam_type]),
                _fmt(unseen["oracle_mae_db"][beam_type]),
                _fmt(unseen["trivial_mae_db"][beam_type]),
            ))  # fmt: skip
    aps = metrics["aps"]
    if aps["pairs"]:
        rows.append((f"APS NMSE [dB] (mean / median over {aps['pairs']} pairs)",
                     f"{_fmt(aps['nmse_db'])} / {_fmt(aps['nmse_db_median'])}", "0 (reference)", "–"))  # fmt: skip
        rows.append(
            (f"APS angle error, top {aps['top_k']} bins [deg]", _fmt(aps["angle_error_deg"]), "0 (reference)", "–")
        )
    return rows


def _markdown_table(metrics: dict[str, Any]) -> str:
    lines = ["| metric | model | oracle | trivial |", "|---|---:|---:|---:|"]
    lines += [f"| {a} | {b} | {c} | {d} |" for a, b, c, d in metric_rows(metrics)]
    return "\n".join(lines)


def _best_beam_per_grid(res: BeamResult) -> pd.DataFrame:
    """Measured and predicted best-beam RSRP [dBm] per grid over the scored (cell, grid) pairs."""
    rows = res.scored
    with np.errstate(all="ignore"):
        frame = pd.DataFrame({
            "grid_id": res.pairs["grid_id"].to_numpy()[rows],
            "measured": np.nanmax(np.where(np.isfinite(res.measured[rows]), res.measured[rows], -np.inf), axis=1),
            "predicted": np.nanmax(np.where(np.isfinite(res.model[rows]), res.model[rows], -np.inf), axis=1),
        })  # fmt: skip
    best = frame.groupby("grid_id").max().replace(-np.inf, np.nan)
    return best.reset_index()


def _coverage_figure(evaluation: Evaluation, scenario: Scenario, out: Path, title: str) -> tuple[Path | None, str]:
    beam_type = "ssb" if evaluation.beams["ssb"].scored.any() else "csi"
    res = evaluation.beams[beam_type]
    if not res.scored.any():
        return None, "The model predicted no test pair, so there is no predicted coverage map."
    best = _best_beam_per_grid(res)
    grids = scenario.grids.set_index("grid_id").loc[best["grid_id"], ["x", "y"]].to_numpy()
    cells = scenario.cells[evaluation.test_round]
    changed = cells["cell_id"].isin(evaluation.metrics["counts"]["changed_cells"]).to_numpy()
    path = plots.coverage_maps(
        out / "coverage.png", grids, best["measured"].to_numpy(), best["predicted"].to_numpy(),
        cells[["x", "y"]].to_numpy(), cells["azimuth_deg"].to_numpy(), changed,
        f"{title}: round-{evaluation.test_round} {beam_type.upper()} coverage",
    )  # fmt: skip
    return path, (
        f"Best {beam_type.upper()}-beam RSRP per grid in round {evaluation.test_round}, measured (reported beams) vs "
        f"predicted (every beam of the same cells), and their difference.  The maximum over noisy measured "
        f"beams is biased upwards by the noise, so a slightly negative difference is expected even for a perfect model."
    )


def _signed_errors(evaluation: Evaluation) -> dict[str, dict[str, np.ndarray]]:
    out: dict[str, dict[str, np.ndarray]] = {}
    for beam_type, res in evaluation.beams.items():
        rows = res.rows()
        by_name = {"model": (res.model[rows] - res.measured[rows]).ravel(),
                   "trivial": (res.trivial[rows] - res.measured[rows]).ravel()}  # fmt: skip
        if res.oracle is not None:
            by_name["oracle"] = (res.oracle[rows] - res.measured[rows]).ravel()
        out[beam_type] = by_name
    return out


def _aps_figure(evaluation: Evaluation, scenario: Scenario, model: Any, out: Path) -> Path | None:
    if (
        evaluation.aps_pairs is None
        or not len(evaluation.aps_pairs)
        or evaluation.aps_true is None
        or evaluation.aps_est is None
    ):
        return None
    power = evaluation.aps_true.astype(np.float64).sum(1)
    order = np.argsort(-power)
    picks = sorted({int(order[int(q * (len(order) - 1))]) for q in (0.1, 0.5, 0.9)})[:APS_EXAMPLES]
    pairs = evaluation.aps_pairs.iloc[picks]
    labels = [f"cell {c}, grid {g}" for c, g in zip(pairs["cell_id"], pairs["grid_id"])]
    cells = scenario.cells[1].set_index("cell_id")
    boresight = cells.loc[pairs["cell_id"], "azimuth_deg"].to_numpy()  # clockwise from north, as the plot
    return plots.aps_heatmaps(
        out / "aps.png",
        model.angle_grid,
        labels,
        evaluation.aps_true[picks],
        evaluation.aps_est[picks],
        boresight_az_deg=[float(b) for b in boresight],
    )


def write_report(evaluation: Evaluation, scenario: Scenario, model: Any, out_dir: str | Path) -> Path:
    """Write ``report.md``, ``metrics.json`` and the PNG figures into ``out_dir``; returns the Markdown path."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    m = evaluation.metrics
    title = f"{m['model']['name']} on {m['scenario']['name']} ({m['protocol']['name']})"
    (out / "metrics.json").write_text(json.dumps(m, indent=2))
    sections = [f"# Evaluation: {title}", "", _summary_lines(m), "", _markdown_table(m), ""]
    if m["unsupported"]:
        sections += [f"> Note: {m['unsupported']}", ""]
    coverage, caption = _coverage_figure(evaluation, scenario, out, title)
    sections += ["## Coverage", "", caption, ""] + ([f"![coverage maps]({coverage.name})", ""] if coverage else [])
    hist = plots.error_histograms(out / "errors.png", _signed_errors(evaluation), f"{title}: RSRP errors")
    sections += ["## Errors", "", "Signed error of every scored reported beam (model, oracle floor, trivial baseline).",
                 "", f"![error histograms]({hist.name})", ""]  # fmt: skip
    bars = plots.per_cell_bars(out / "per_cell.png", m["per_cell"], f"{title}: MAE per cell")
    sections += ["## Per cell", "", f"![per-cell MAE]({bars.name})", "", _per_cell_table(m["per_cell"]), ""]
    aps = _aps_figure(evaluation, scenario, model, out)
    if aps is not None:
        sections += ["## Angular power spectra", "", "True (binned ray-tracer paths) vs estimated APS for three test "
                     "pairs (strong, median and weak received power).", "", f"![APS heat maps]({aps.name})", ""]  # fmt: skip
    path = out / "report.md"
    path.write_text("\n".join(sections))
    return path


def _summary_lines(m: dict[str, Any]) -> str:
    counts = m["counts"]
    settings = ", ".join(f"{k}={v}" for k, v in m["protocol"].items() if k != "name") or "defaults"
    return "\n".join([
        f"- scenario: `{m['scenario']['name']}` ({m['scenario']['root']})",
        f"- model: `{m['model']['name']}`; protocol: `{m['protocol']['name']}` ({settings}); test round {m['test_round']}",
        f"- scored: {counts['ssb']['scored_pairs']}/{counts['ssb']['test_pairs']} SSB and "
        f"{counts['csi']['scored_pairs']}/{counts['csi']['test_pairs']} CSI-RS (cell, grid) pairs; "
        f"{counts['ssb']['beams']} + {counts['csi']['beams']} reported beams",
        f"- changed cells: {', '.join(map(str, counts['changed_cells'])) or 'none'}",
    ])  # fmt: skip


def _per_cell_table(per_cell: dict[str, Any]) -> str:
    lines = ["| cell | changed | SSB model | SSB oracle | SSB trivial | CSI model | CSI oracle | CSI trivial |",
             "|---|:---:|---:|---:|---:|---:|---:|---:|"]  # fmt: skip
    for cell, e in per_cell.items():
        lines.append(
            f"| {cell} | {'yes' if e['changed'] else ''} | {_fmt(e['ssb'])} | {_fmt(e['oracle']['ssb'])} | "
            f"{_fmt(e['trivial']['ssb'])} | {_fmt(e['csi'])} | {_fmt(e['oracle']['csi'])} | {_fmt(e['trivial']['csi'])} |"
        )
    return "\n".join(lines)
