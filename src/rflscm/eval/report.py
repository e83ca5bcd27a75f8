"""The evaluation report: ``report.md`` with the metric table and PNG figures: coverage, network maps (best server,
serving cell, SS-SINR, their differences), error CDFs per beam type, per-cell MAE and APS heat maps."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from rflscm.data import BEAM_TYPES
from rflscm.eval import plots
from rflscm.eval.evaluate import BeamResult, Evaluation

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.models.source import APSSource

APS_EXAMPLES = 3


def _fmt(value: float | None, unit: str = "") -> str:
    return "–" if value is None else f"{value:.2f}{unit}"


def metric_rows(metrics: dict[str, Any]) -> list[tuple[str, str, str, str]]:
    """``(metric, model, oracle, trivial)`` rows of the summary table, as text."""
    rows = []
    for beam_type in BEAM_TYPES:
        for subset in ("all", "changed"):
            if subset == "changed" and metrics["mae_db"][beam_type]["changed"] is None:
                continue
            rows.append(
                (
                    f"MAE {beam_type.upper()}, {subset} cells [dB]",
                    _fmt(metrics["mae_db"][beam_type][subset]),
                    _fmt(metrics["oracle_mae_db"][beam_type][subset]),
                    _fmt(metrics["trivial_mae_db"][beam_type][subset]),
                )
            )
    unseen = metrics["unseen"]
    for beam_type in BEAM_TYPES:
        if unseen["pairs"][beam_type]:
            rows.append(
                (
                    f"MAE {beam_type.upper()}, unseen pairs [dB] (n={unseen['pairs'][beam_type]})",
                    _fmt(unseen["mae_db"][beam_type]),
                    _fmt(unseen["oracle_mae_db"][beam_type]),
                    _fmt(unseen["trivial_mae_db"][beam_type]),
                )
            )
    aps = metrics["aps"]
    if aps["pairs"]:
        rows.append(
            (
                f"APS NMSE against the true APS [dB] (mean / median over {aps['pairs']} pairs; an all-zero "
                "APS scores 0 dB, lower is better)",
                f"{_fmt(aps['nmse_db'])} / {_fmt(aps['nmse_db_median'])}",
                "– (is the reference)",
                "–",
            )
        )
        rows.append(
            (
                f"APS angle error against the true APS, top {aps['top_k']} bins [deg]",
                _fmt(aps["angle_error_deg"]),
                "– (is the reference)",
                "–",
            )
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
        frame = pd.DataFrame(
            {
                "grid_id": res.pairs["grid_id"].to_numpy()[rows],
                "measured": np.nanmax(np.where(np.isfinite(res.measured[rows]), res.measured[rows], -np.inf), axis=1),
                "predicted": np.nanmax(np.where(np.isfinite(res.model[rows]), res.model[rows], -np.inf), axis=1),
            }
        )
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
        out / "coverage.png",
        grids,
        best["measured"].to_numpy(),
        best["predicted"].to_numpy(),
        cells[["x", "y"]].to_numpy(),
        cells["azimuth_deg"].to_numpy(),
        changed,
        f"{title}: round-{evaluation.test_round} {beam_type.upper()} coverage",
    )
    return path, (
        f"Best {beam_type.upper()}-beam RSRP per grid in round {evaluation.test_round}, measured (reported beams) vs "
        f"predicted (every beam of the same cells), and their difference.  The maximum over noisy measured "
        f"beams is biased upwards by the noise, so a slightly negative difference is expected even for a perfect model."
    )


def _signed_errors(evaluation: Evaluation) -> dict[str, dict[str, np.ndarray]]:
    out: dict[str, dict[str, np.ndarray]] = {}
    for beam_type, res in evaluation.beams.items():
        rows = res.rows()
        by_name = {
            "model": (res.model[rows] - res.measured[rows]).ravel(),
            "trivial": (res.trivial[rows] - res.measured[rows]).ravel(),
        }
        if res.oracle is not None:
            by_name["oracle"] = (res.oracle[rows] - res.measured[rows]).ravel()
        out[beam_type] = by_name
    return out


def _aps_figure(evaluation: Evaluation, scenario: Scenario, model: APSSource, out: Path) -> Path | None:
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


def write_report(evaluation: Evaluation, scenario: Scenario, model: APSSource, out_dir: str | Path) -> Path:
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
    sections += _network_section(evaluation, scenario, out, title)
    errors = _signed_errors(evaluation)
    cdf = plots.error_cdfs(out / "error_cdf.png", errors, f"{title}: RSRP error CDFs")
    hist = plots.error_histograms(out / "errors.png", errors, f"{title}: RSRP errors")
    sections += [
        "## Errors",
        "",
        "Absolute error of every scored reported beam, per beam type, as a CDF (model, "
        "oracle floor, trivial baseline; the oracle is absent without ground truth), then the signed errors.",
        "",
        f"![error CDFs]({cdf.name})",
        "",
        f"![error histograms]({hist.name})",
        "",
    ]
    bars = plots.per_cell_bars(out / "per_cell.png", m["per_cell"], f"{title}: MAE per cell")
    sections += [
        "## Per cell",
        "",
        f"![per-cell MAE]({bars.name})",
        "",
        _per_cell_table(m["per_cell"], _pair_counts(evaluation)),
        "",
    ]
    aps = _aps_figure(evaluation, scenario, model, out)
    if aps is not None:
        sections += [
            "## Angular power spectra",
            "",
            "True (binned ray-tracer paths) vs estimated APS for three test "
            "pairs (strong, median and weak received power).",
            "",
            f"![APS heat maps]({aps.name})",
            "",
        ]
    path = out / "report.md"
    path.write_text("\n".join(sections))
    return path


def _summary_lines(m: dict[str, Any]) -> str:
    counts = m["counts"]
    settings = ", ".join(f"{k}={v}" for k, v in m["protocol"].items() if k != "name") or "defaults"
    return "\n".join(
        [
            f"- scenario: `{m['scenario']['name']}` ({m['scenario']['root']})",
            f"- model: `{m['model']['name']}`; protocol: `{m['protocol']['name']}` ({settings}); test round {m['test_round']}",
            f"- scored: {counts['ssb']['scored_pairs']}/{counts['ssb']['test_pairs']} SSB and "
            f"{counts['csi']['scored_pairs']}/{counts['csi']['test_pairs']} CSI-RS (cell, grid) pairs; "
            f"{counts['ssb']['beams']} + {counts['csi']['beams']} reported beams",
            f"- changed cells: {', '.join(map(str, counts['changed_cells'])) or 'none'}",
        ]
    )


FEW_PAIRS = 5
"""A per-cell MAE over fewer (cell, grid) pairs than this is marked as resting on few pairs."""


def _pair_counts(evaluation: Evaluation) -> dict[str, dict[str, int]]:
    """Scored (cell, grid) pairs per cell and beam type (what each per-cell MAE rests on)."""
    out: dict[str, dict[str, int]] = {}
    for beam_type, res in evaluation.beams.items():
        cells = res.pairs["cell_id"].to_numpy()[res.rows()]
        for cell, n in zip(*np.unique(cells, return_counts=True)):
            out.setdefault(str(int(cell)), {})[beam_type] = int(n)
    return out


def _per_cell_table(per_cell: dict[str, Any], pairs: dict[str, dict[str, int]] | None = None) -> str:
    pairs = pairs or {}
    lines = [
        "MAE per cell (dB) and the number of scored (cell, grid) pairs it rests on; ⚠ marks fewer than "
        f"{FEW_PAIRS} pairs, too few to judge the cell.",
        "",
        "| cell | changed | SSB pairs | SSB model | SSB oracle | SSB trivial | CSI pairs | CSI model | CSI oracle | "
        "CSI trivial |",
        "|---|:---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for cell, e in per_cell.items():
        n = pairs.get(cell, {})
        count = {bt: f"{n.get(bt, 0)} ⚠" if 0 < n.get(bt, 0) < FEW_PAIRS else str(n.get(bt, 0)) for bt in BEAM_TYPES}
        lines.append(
            f"| {cell} | {'yes' if e['changed'] else ''} | {count['ssb']} | {_fmt(e['ssb'])} | "
            f"{_fmt(e['oracle']['ssb'])} | {_fmt(e['trivial']['ssb'])} | {count['csi']} | {_fmt(e['csi'])} | "
            f"{_fmt(e['oracle']['csi'])} | {_fmt(e['trivial']['csi'])} |"
        )
    return "\n".join(lines)


def _layers(m: Any) -> dict[str, np.ndarray]:
    v = m.valid
    return {
        "rsrp_dbm": np.where(v, m.best_rsrp_dbm, np.nan),
        "serving": np.where(v, m.serving_cell, -1),
        "sinr_db": np.where(v, m.sinr_db, np.nan),
    }


def _network_section(evaluation: Evaluation, scenario: Scenario, out: Path, title: str) -> list[str]:
    """Best-server RSRP, serving cell and SS-SINR maps, measured and predicted on the same scored SSB pairs, and
    their differences, one PNG per carrier; with the network KPIs (rflscm.network.kpi) of both."""
    from rflscm.network.kpi import KPIConfig, best_beam_power_from_rsrp, grid_maps, network_kpis

    res = evaluation.beams["ssb"]
    rows = res.scored
    if not rows.any():
        return []
    pairs = res.pairs.iloc[np.flatnonzero(rows)]
    cell_ids, grid_ids = scenario.cell_ids(), scenario.grid_ids()
    pc, pg = pairs["cell_id"].to_numpy(), pairs["grid_id"].to_numpy()
    measured, known = best_beam_power_from_rsrp(res.measured[rows], pc, pg, cell_ids, grid_ids)
    predicted, _ = best_beam_power_from_rsrp(res.model[rows], pc, pg, cell_ids, grid_ids)
    freqs = np.array([scenario.freq_hz(int(c)) for c in cell_ids])
    kpi = KPIConfig()
    cells = scenario.cells[evaluation.test_round].set_index("cell_id").loc[cell_ids]
    changed = np.isin(cell_ids, evaluation.metrics["counts"]["changed_cells"])
    xy = scenario.grids.set_index("grid_id").loc[grid_ids, ["x", "y"]].to_numpy()
    lines = [
        "## Network maps",
        "",
        f"Best-server SSB RSRP, serving cell and SS-SINR per grid in round {evaluation.test_round}, measured "
        "(strongest reported beam of each pair) and predicted (strongest of every beam) over the same "
        f"{int(known.sum())} scored (cell, grid) pairs, and predicted − measured. SS-SINR counts the cells "
        "measured at a grid as its interferers (rflscm.network.kpi).",
        "",
        "| KPI | measured | predicted | predicted − measured |",
        "| --- | ---: | ---: | ---: |",
    ]
    km, kp = network_kpis(measured, freqs, kpi, known), network_kpis(predicted, freqs, kpi, known)
    for key, label, scale in (
        ("coverage", f"coverage, RSRP ≥ {kpi.threshold_dbm:g} dBm (%)", 100.0),
        ("mean_sinr_db", "mean SS-SINR (dB)", 1.0),
        ("overlap", "overlap (%)", 100.0),
        ("mean_rsrp_dbm", "mean best-server RSRP (dBm)", 1.0),
    ):
        lines.append(
            f"| {label} | {km[key] * scale:.2f} | {kp[key] * scale:.2f} | {(kp[key] - km[key]) * scale:+.2f} |"
        )
    lines.append("")
    for mm, mp in zip(
        grid_maps(measured, cell_ids, freqs, kpi, known), grid_maps(predicted, cell_ids, freqs, kpi, known)
    ):
        on = freqs == mm.freq_hz
        name = f"network_{mm.freq_hz / 1e9:g}GHz.png"
        plots.kpi_maps(
            out / name,
            xy,
            [("measured", _layers(mm)), ("predicted", _layers(mp))],
            cell_ids[on],
            cells[["x", "y"]].to_numpy()[on],
            cells["azimuth_deg"].to_numpy()[on],
            changed[on],
            f"{title}: {mm.freq_hz / 1e9:g} GHz, round {evaluation.test_round}",
            difference=("predicted − measured", 0, 1),
        )
        lines += [f"![network maps {mm.freq_hz / 1e9:g} GHz]({name})", ""]
    return lines


DB_PER_NEPER = 20.0 / np.log(10.0)


def learned_attenuation(model: Any, cells_per_side: int = 160, heights: int = 24) -> tuple[np.ndarray, ...]:
    """The attenuation a radiance-field model (RF-LSCM, NeRF²) learned, seen from above.

    Samples the δ field of the model's last rendering stage on a ``cells_per_side`` × ``cells_per_side`` ×
    ``heights`` lattice over the scene box and returns ``(x_m [nx], y_m [ny], db_per_m [ny, nx])``: the largest
    one-way loss −log|δ| over height at the reference carrier, per metre (the medium's own conversion of δ's
    loss channel).

    Raises:
        ConfigError: the model has no attenuation field (WNOMP), or has not been trained.
    """
    import torch

    from rflscm.errors import ConfigError

    stages = getattr(model, "all_stages", None)
    scene = getattr(model, "scene", None)
    if stages is None or scene is None or not stages():
        raise ConfigError(f"{model.name} has no attenuation field; --attenuation-map needs an rflscm or nerf2 model.")
    stage = stages()[-1]
    frame = scene.frame
    lo, hi = np.asarray(frame.box_lo, dtype=np.float64), np.asarray(frame.box_hi, dtype=np.float64)
    xs, ys, zs = (
        lo[k] + (np.arange(n) + 0.5) * (hi[k] - lo[k]) / n
        for k, n in ((0, cells_per_side), (1, cells_per_side), (2, heights))
    )
    grid = np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)  # [nx·ny·nz, 3]
    device = next(stage.parameters()).device
    step_m = stage.medium.voxel_m
    out = []
    with torch.no_grad():
        for chunk in np.array_split(grid, max(1, len(grid) // 65536)):
            points = torch.as_tensor(chunk, dtype=torch.float32, device=device)
            raw = stage.fields.delta(stage.fields.encode(points))
            out.append((stage.medium.loss_db(raw) / step_m).double().cpu().numpy())
    loss = np.concatenate(out).reshape(len(xs), len(ys), len(zs))
    return xs, ys, loss.max(axis=2).T


def write_attenuation_map(model: Any, scenario: Scenario, path: str | Path, round: int = 1) -> Path:
    """PNG of :func:`learned_attenuation` with the scenario's sites and cell azimuths (round ``round``)."""
    xs, ys, db_per_m = learned_attenuation(model)
    cells = scenario.cells[round] if round in scenario.cells else scenario.cells[1]
    return plots.attenuation_map(
        Path(path),
        xs,
        ys,
        db_per_m,
        f"{model.name}: learned attenuation over {scenario.meta.name}",
        cells[["x", "y"]].to_numpy(),
        cells["azimuth_deg"].to_numpy(),
    )
