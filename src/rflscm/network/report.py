"""The Markdown report of ``rflscm optimize``: KPI table (predicted and true), changes, before/after maps."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from rflscm.network.kpi import KPIConfig, grid_maps

if TYPE_CHECKING:
    import pandas as pd

    from rflscm.data.scenario import Scenario
    from rflscm.network.optimize import OptimizeResult

KPI_ROWS = (
    ("coverage", "coverage ratio", 100.0, "%"),
    ("mean_sinr_db", "mean SS-SINR", 1.0, "dB"),
    ("p5_sinr_db", "5th-percentile SS-SINR", 1.0, "dB"),
    ("overlap", "overlap ratio", 100.0, "%"),
    ("mean_rsrp_dbm", "mean best-server RSRP", 1.0, "dBm"),
    ("no_signal", "no signal at all", 100.0, "%"),
)


def _row(label: str, unit: str, scale: float, kpis: dict[str, Any], key: str) -> str:
    b, a = kpis["before"][key] * scale, kpis["after"][key] * scale
    return f" {b:.2f} | {a:.2f} | {a - b:+.2f} |"


def kpi_table(result: OptimizeResult) -> list[str]:
    """Markdown rows: KPI | predicted before | after | gain | (true before | after | gain) | (held-out gain),
    the predicted and true columns on the same (cell, grid) pairs."""
    truth, held = result.truth, result.held_out
    head = "| KPI | predicted before | predicted after | predicted gain |"
    rule = "| --- | ---: | ---: | ---: |"
    if truth is not None:
        head += " true before | true after | true gain |"
        rule += " ---: | ---: | ---: |"
    if held is not None:
        head += f" predicted gain, {result.held_out_grids} held-out grids |"
        rule += " ---: |"
    lines = [head, rule]
    for key, label, scale, unit in KPI_ROWS:
        row = f"| {label} ({unit}) |" + _row(label, unit, scale, result.predicted, key)
        if truth is not None:
            row += _row(label, unit, scale, truth, key)
        if held is not None:
            row += f" {(held['after'][key] - held['before'][key]) * scale:+.2f} |"
        lines.append(row)
    return lines


def verdict_markdown(verdict: dict[str, Any]) -> str:
    """The recommendation's check as one Markdown line: red and bold when it is flagged."""
    if verdict["flagged"]:
        return f'<span style="color:red">**⚠ {verdict["text"]}.**</span>'
    if verdict["basis"] is None:
        return f"Check: {verdict['text']}."
    return f"Check passed: {verdict['text']}."


def gap_lines(result: OptimizeResult, summary: dict[str, Any]) -> list[str]:
    """Why predicted and true KPIs differ in level although they cover the same pairs."""
    if result.truth is None:
        return []
    gap = summary["level_gap"]
    lines = [
        f"Predicted and true KPIs cover the same {summary['kpi_pair_count']} (cell, grid) pairs "
        f"({summary['kpi_pairs']}). Their remaining difference in level is the model's error on these pairs, "
        f"not a difference of scope: before the change the model puts the mean best-server RSRP "
        f"{gap['mean_rsrp_dbm']:+.2f} dB, coverage {gap['coverage'] * 100:+.2f} points and mean SS-SINR "
        f"{gap['mean_sinr_db']:+.2f} dB off the truth (which is the noiseless expectation, while the model learned "
        "from noisy, quantised reports). Judge a recommendation by its gains, which the same bias largely cancels "
        "in, not by the levels.",
    ]
    if result.truth_all is not None:
        ta = result.truth_all
        lines += [
            "",
            "The model has an APS only for the measured round-1 pairs: a grid's best server and interferers are "
            "those measured there, so unmeasured cells count as silent and the KPIs read better than over every "
            "pair. The truth over every (cell, grid) pair, for scale:",
            "",
            "| KPI | true before, every pair | true after, every pair | true gain, every pair |",
            "| --- | ---: | ---: | ---: |",
        ]
        lines += [f"| {label} ({unit}) |" + _row(label, unit, scale, ta, key) for key, label, scale, unit in KPI_ROWS]
    return lines


def write_report(
    result: OptimizeResult,
    scenario: Scenario,
    out_dir: Path,
    kpi: KPIConfig,
    round_written: int,
    scenario_dir: Path,
    command: str = "",
) -> Path:
    """Write ``report.md``, ``summary.json``, ``changes.csv`` and the map PNGs into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = result.summary()
    summary["kpi_constants"] = kpi.describe(list(scenario.meta.frequencies_hz))
    summary["round"] = {"number": round_written, "scenario": str(scenario_dir)}
    (out_dir / "summary.json").write_text(json.dumps(summary, indent=2, default=float))
    result.changes.to_csv(out_dir / "changes.csv", index=False)
    maps = _maps(result, scenario, out_dir, kpi)
    s = result.search
    held = (
        f" The search scored {len(scenario.grid_ids()) - result.held_out_grids} grids and never saw the other "
        f"{result.held_out_grids} (held out), whose predicted gain checks the recommendation."
        if result.held_out is not None
        else ""
    )
    lines = [
        f"# rflscm optimize — {scenario.meta.name}",
        "",
        verdict_markdown(summary["verdict"]),
        "",
        f"Model **{result.model}**, objective **{result.objective}**, search **{s.method}**: "
        f"{s.evaluations} single-cell candidate evaluations in {s.time_s:.1f} s "
        f"({s.evaluations / max(s.time_s, 1e-9):.0f}/s); objective {s.base_objective:.4f} → {s.objective:.4f}.{held}",
        "",
        f"KPIs on {summary['kpi_pairs']} ({summary['kpi_pair_count']} (cell, grid) pairs), predicted and true alike. "
        f"SS-SINR: serving cell against every other cell's best SSB beam on the same carrier plus thermal noise "
        f"per resource element (constants below). Coverage: best-server SSB RSRP ≥ {kpi.threshold_dbm:g} dBm.",
    ]
    if result.truth is not None:
        lines += ["", f"True KPIs: {result.truth['note']}."]
    else:
        lines += ["", "No `truth/` in this scenario: predicted KPIs only."]
    lines += ["", "## KPIs", "", *kpi_table(result), ""]
    if result.truth is not None:
        lines += ["### Predicted against true", "", *gap_lines(result, summary), ""]
    lines += ["## Changed cells", ""]
    lines += _changes_md(result.changes)
    lines += [
        "",
        f"Written as round {round_written} of `{scenario_dir / 'scenario.yaml'}` (it names the original "
        f"scenario's files by relative paths); `rflscm predict CKPT {scenario_dir} --round {round_written} "
        f"--pairs {'measured' if result.known is not None else 'all'} --kpi` reproduces the predicted KPIs.",
        "",
        "## Maps (predicted)",
        "",
    ]
    lines += [f"![{m}]({m})" for m in maps]
    lines += [
        "",
        "## KPI constants",
        "",
        "```json",
        json.dumps(summary["kpi_constants"], indent=2),
        "```",
    ]
    if command:
        lines += ["", f"Command: `{command}`"]
    path = out_dir / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _changes_md(changes: pd.DataFrame) -> list[str]:
    if len(changes) == 0:
        return ["No cell changed: the present configuration is the best found."]
    lines = [
        "| cell | site | carrier (GHz) | SSB codebook | elec. tilt (°) | mech. tilt (°) | azimuth (°, clockwise from north) |",
        "| ---: | ---: | ---: | --- | --- | --- | --- |",
    ]
    for r in changes.itertuples(index=False):
        lines.append(
            f"| {r.cell_id} | {r.site_id} | {r.freq_hz / 1e9:g} | {r.ssb_codebook_before} → {r.ssb_codebook_after} | "
            f"{r.elec_tilt_deg_before:g} → {r.elec_tilt_deg_after:g} | {r.mech_tilt_deg_before:g} → "
            f"{r.mech_tilt_deg_after:g} | {r.azimuth_deg_before:g} → {r.azimuth_deg_after:g} |"
        )
    return lines


def _maps(result: OptimizeResult, scenario: Scenario, out_dir: Path, kpi: KPIConfig) -> list[str]:
    """One PNG per carrier: rows before / after / difference; columns best-server RSRP, serving cell, SS-SINR."""
    from rflscm.eval.plots import kpi_maps

    cells = result.cells_before
    cell_ids = cells["cell_id"].to_numpy()
    freqs = cells["freq_hz"].to_numpy()
    xy = scenario.grids.set_index("grid_id").loc[scenario.grid_ids(), ["x", "y"]].to_numpy()
    changed = cells["cell_id"].isin(result.changes["cell_id"]).to_numpy()
    after_az = result.cells_after["azimuth_deg"].to_numpy()
    before = grid_maps(result.power_before, cell_ids, freqs, kpi, result.known)
    after = grid_maps(result.power_after, cell_ids, freqs, kpi, result.known)
    names = []
    for mb, ma in zip(before, after):
        on = freqs == mb.freq_hz
        rows = [(label, _layers(m)) for label, m in (("before", mb), ("after", ma))]
        name = f"maps_{mb.freq_hz / 1e9:g}GHz.png"
        kpi_maps(
            out_dir / name,
            xy,
            rows,
            cell_ids[on],
            cells[["x", "y"]].to_numpy()[on],
            after_az[on],
            changed[on],
            f"{mb.freq_hz / 1e9:g} GHz, model {result.model}: predicted before and after (arrows: after)",
            difference=("after − before", 0, 1),
        )
        names.append(name)
    return names


def _layers(m: Any) -> dict[str, np.ndarray]:
    v = m.valid
    return {
        "rsrp_dbm": np.where(v, m.best_rsrp_dbm, np.nan),
        "serving": np.where(v, m.serving_cell, -1),
        "sinr_db": np.where(v, m.sinr_db, np.nan),
    }
