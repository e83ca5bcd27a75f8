"""The Markdown report of ``rflscm optimize``: KPI table (predicted and true), changes, before/after maps."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from rflscm.network.kpi import KPIConfig, grid_maps

if TYPE_CHECKING:
    import pandas as pd

    from rflscm.data.scenario import Scenario
    from rflscm.network.optimize import OptimizeResult

KPI_ROWS = (("coverage", "coverage ratio", 100.0, "%"), ("mean_sinr_db", "mean SS-SINR", 1.0, "dB"),
            ("p5_sinr_db", "5th-percentile SS-SINR", 1.0, "dB"), ("overlap", "overlap ratio", 100.0, "%"),
            ("mean_rsrp_dbm", "mean best-server RSRP", 1.0, "dBm"),
            ("no_signal", "no signal at all", 100.0, "%"))  # fmt: skip


def kpi_table(result: OptimizeResult) -> list[str]:
    """Markdown rows: KPI | predicted before | after | gain | (true before | after | gain)."""
    truth = result.truth
    head = "| KPI | predicted before | predicted after | predicted gain |"
    rule = "| --- | ---: | ---: | ---: |"
    if truth is not None:
        head += " true before | true after | true gain |"
        rule += " ---: | ---: | ---: |"
    lines = [head, rule]
    for key, label, scale, unit in KPI_ROWS:
        p = result.predicted
        row = f"| {label} [{unit}] | {p['before'][key] * scale:.2f} | {p['after'][key] * scale:.2f} | " \
              f"{(p['after'][key] - p['before'][key]) * scale:+.2f} |"  # fmt: skip
        if truth is not None:
            row += f" {truth['before'][key] * scale:.2f} | {truth['after'][key] * scale:.2f} | " \
                   f"{(truth['after'][key] - truth['before'][key]) * scale:+.2f} |"  # fmt: skip
        lines.append(row)
    return lines


def write_report(result: OptimizeResult, scenario: Scenario, out_dir: Path, kpi: KPIConfig, round_written: int,
                 scenario_dir: Path, command: str = "") -> Path:  # fmt: skip
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
    lines = [
        f"# rflscm optimize — {scenario.meta.name}", "",
        f"Model **{result.model}**, objective **{result.objective}**, search **{s.method}**: "
        f"{s.evaluations} single-cell candidate evaluations in {s.time_s:.1f} s "
        f"({s.evaluations / max(s.time_s, 1e-9):.0f}/s); objective {s.base_objective:.4f} → {s.objective:.4f}.",
        "",
        f"KPIs on {summary['kpi_pairs']}. SS-SINR: serving cell against every other cell's best SSB beam on the "
        f"same carrier plus thermal noise per resource element (constants below). Coverage: best-server SSB "
        f"RSRP ≥ {kpi.threshold_dbm:g} dBm.",
    ]  # fmt: skip
    if result.truth is not None:
        lines += ["", f"True KPIs: {result.truth['note']}."]
    else:
        lines += ["", "No `truth/` in this scenario: predicted KPIs only."]
    lines += ["", "## KPIs", "", *kpi_table(result), "", "## Changed cells", ""]
    lines += _changes_md(result.changes)
    lines += ["", f"Written as round {round_written} of `{scenario_dir / 'scenario.yaml'}`; "
              f"`rflscm predict CKPT {scenario_dir} --round {round_written} --pairs all --kpi` reproduces the "
              "predicted KPIs.", "", "## Maps (predicted)", ""]  # fmt: skip
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
    lines = ["| cell | site | carrier [GHz] | SSB codebook | elec. tilt [°] | mech. tilt [°] | azimuth [°] |",
             "| ---: | ---: | ---: | --- | --- | --- | --- |"]  # fmt: skip
    for r in changes.itertuples(index=False):
        lines.append(
            f"| {r.cell_id} | {r.site_id} | {r.freq_hz / 1e9:g} | {r.ssb_codebook_before} → {r.ssb_codebook_after} | "
            f"{r.elec_tilt_deg_before:g} → {r.elec_tilt_deg_after:g} | {r.mech_tilt_deg_before:g} → "
            f"{r.mech_tilt_deg_after:g} | {r.azimuth_deg_before:g} → {r.azimuth_deg_after:g} |"
        )
    return lines


def _maps(result: OptimizeResult, scenario: Scenario, out_dir: Path, kpi: KPIConfig) -> list[str]:
    """One PNG per carrier: rows before/after, columns best-server RSRP, serving cell, SS-SINR."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cell_ids = result.cells_before["cell_id"].to_numpy()
    freqs = result.cells_before["freq_hz"].to_numpy()
    xy = scenario.grids[["x", "y"]].to_numpy()
    before = grid_maps(result.power_before, cell_ids, freqs, kpi, result.known)
    after = grid_maps(result.power_after, cell_ids, freqs, kpi, result.known)
    names = []
    for mb, ma in zip(before, after):
        fig, axes = plt.subplots(2, 3, figsize=(15, 9), squeeze=False)
        for row, (label, m) in enumerate((("before", mb), ("after", ma))):
            v = m.valid
            panels = ((m.best_rsrp_dbm, "best-server RSRP [dBm]", "viridis", (-130, -60)),
                      (m.serving_cell, "serving cell", "tab20", None),
                      (m.sinr_db, "SS-SINR [dB]", "RdYlGn", (-10, 30)))  # fmt: skip
            for col, (values, title, cmap, lim) in enumerate(panels):
                ax = axes[row, col]
                if lim is None:
                    codes = np.searchsorted(cell_ids, values[v])  # the same colour per cell before and after
                    sc = ax.scatter(
                        xy[v, 0],
                        xy[v, 1],
                        c=codes % 20,
                        cmap=cmap,
                        s=9,
                        vmin=0,
                        vmax=19,
                    )
                else:
                    sc = ax.scatter(
                        xy[v, 0],
                        xy[v, 1],
                        c=values[v],
                        cmap=cmap,
                        s=9,
                        vmin=lim[0],
                        vmax=lim[1],
                    )
                    fig.colorbar(sc, ax=ax, shrink=0.8)
                ax.set_title(f"{label}: {title}")
                ax.set_aspect("equal")
        fig.suptitle(f"{mb.freq_hz / 1e9:g} GHz, model {result.model}")
        name = f"maps_{mb.freq_hz / 1e9:g}GHz.png"
        fig.savefig(out_dir / name, dpi=90, bbox_inches="tight")
        plt.close(fig)
        names.append(name)
    return names
