"""``rflscm demo``: WNOMP vs RF-LSCM on the shipped scenario, antenna-adjustment MAE beside the oracle floor."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import typer
from rich.console import Console
from rich.table import Table

from rflscm.cli import app
from rflscm.cli.common import (
    SEED_MAX,
    Device,
    DeviceOption,
    ForceOption,
    SeedOption,
    budget_note,
    budget_seconds,
    budget_summary,
    check_numbers,
    command_start,
    json_text,
    output_folder,
    resolve_device,
    seed_everything,
)
from rflscm.cli.overrides import PresetOption, SetOption, model_config

DEMO_MINUTES = 4.0
"""The demo's default budget, all-in: WNOMP and its evaluation take about 40 s of it on 2 cores, RF-LSCM's fit and
evaluation the rest (its training about 3 minutes on the shipped scenario)."""
MIN_RFLSCM_S = 10.0
"""RF-LSCM's fit gets at least this many seconds, even when WNOMP used up the budget (a warning says so)."""

ROWS = [
    ("SSB MAE, all cells (dB)", ("ssb", "all")),
    ("SSB MAE, changed cells (dB)", ("ssb", "changed")),
    ("CSI-RS MAE, all cells (dB)", ("csi", "all")),
    ("CSI-RS MAE, changed cells (dB)", ("csi", "changed")),
]


def _fmt(value: float | None) -> str:
    return "—" if value is None else f"{value:.2f}"


def _same_pairs(results: dict[str, dict]) -> bool:
    """Whether every model scored the same test pairs: all answer unseen grids, or none do, or there are none."""
    first = next(iter(results.values()))
    unseen = sum((first.get("unseen", {}).get("pairs") or {}).values())
    answers = {bool(r.get("model", {}).get("supports_unseen_grids")) for r in results.values()}
    return unseen == 0 or len(answers) == 1 or any("seen" not in r for r in results.values())


def demo_rows(results: dict[str, dict]) -> tuple[list[str], list[list[str]]]:
    """The comparison as plain text: columns (metric, each model, model floor, noise floor, trivial) and rows (the
    four MAEs, the models' mean signed errors, training time).

    Every MAE row scores each model and the floors on the same pairs.  Where one model answers grids without a
    round-1 report and another does not (RF-LSCM against WNOMP), the four rows are over the pairs with a round-1
    report (each metrics' ``seen`` block), and a row per beam type with such grids gives them (``unseen``), where a
    model that cannot answer shows —."""
    columns = ["metric", *results, "model floor", "noise floor", "trivial"]
    first = next(iter(results.values()))
    same = _same_pairs(results)
    rows = []
    for label, (bt, subset) in ROWS:
        blocks = [r if same else r["seen"] for r in results.values()]
        ref = first if same else first["seen"]
        cells = [_fmt(b["mae_db"][bt][subset]) for b in blocks]
        floors = (ref["oracle_mae_db"][bt][subset], ref.get("noise_floor_mae_db", {}).get(bt, {}).get(subset))
        if not same:
            label = label.replace(" (dB)", ", grids with round-1 reports (dB)")
        rows.append([label, *cells, *(_fmt(f) for f in floors), _fmt(ref["trivial_mae_db"][bt][subset])])
    if not same:
        unseen = first["unseen"]
        for bt, name in (("ssb", "SSB"), ("csi", "CSI-RS")):
            if not unseen["pairs"][bt]:
                continue
            cells = [_fmt(r["unseen"]["mae_db"][bt]) for r in results.values()]
            others = [_fmt(unseen[k][bt]) for k in ("oracle_mae_db", "noise_floor_mae_db", "trivial_mae_db")]
            n = unseen["pairs"][bt]
            rows.append([f"{name} MAE, grids without round-1 reports, {n} pairs (dB)", *cells, *others])
    for bt, name in (("ssb", "SSB"), ("csi", "CSI-RS")):
        bias = [_fmt((r if same else r["seen"]).get("bias_db", {}).get(bt, {}).get("all")) for r in results.values()]
        where = "" if same else ", grids with round-1 reports"
        rows.append([f"{name} mean signed error{where} (dB)", *bias, "", "", ""])
    times = [f"{(r['model']['fit'] or {}).get('train_time_s', float('nan')):.0f}" for r in results.values()]
    rows.append(["training time (s)", *times, "", "", ""])
    return columns, rows


def demo_table(results: dict[str, dict], title: str) -> Table:
    """Rows: the four MAEs and the models' mean signed errors; columns: each model, then the model floor (oracle:
    true APS through the nominal A′), the noise floor (noiseless RSRP through the real antenna) and trivial."""
    columns, rows = demo_rows(results)
    table = Table(title=title)
    table.add_column(columns[0])
    for name in columns[1:]:
        table.add_column(name, justify="right")
    for row in rows:
        table.add_row(*row)
    return table


def save_comparison(results: dict[str, dict], title: str, out: Path) -> list[Path]:
    """Write the comparison table as ``comparison.md``, ``comparison.csv`` and ``comparison.json`` into ``out``."""
    import csv

    columns, rows = demo_rows(results)
    md = [f"# {title}", "", "| " + " | ".join(columns) + " |", "| --- |" + " ---: |" * (len(columns) - 1)]
    md += ["| " + " | ".join(cell or "" for cell in row) + " |" for row in rows]
    md += [
        "",
        "Model floor: the oracle (true APS through the nominal antenna model); noise floor: the noiseless "
        "RSRP through the real antenna against the measurements; trivial: each pair's mean round-1 RSRP (the "
        "cell's mean where the grid has no round-1 report). Every MAE row scores the models on the same pairs. "
        "— marks a value that does not apply.",
    ]
    paths = [out / "comparison.md", out / "comparison.csv", out / "comparison.json"]
    from rflscm.data.safe_io import atomic_write, write_text_atomic

    def write_csv(tmp: Path) -> None:
        with tmp.open("w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(columns)
            writer.writerows(rows)

    write_text_atomic(paths[0], "\n".join(md) + "\n", "comparison table")
    atomic_write(paths[1], write_csv, "comparison table")
    write_text_atomic(paths[2], json_text({"title": title, "columns": columns, "rows": rows}), "comparison table")
    return paths


def rflscm_budget(left_s: float, console: Console) -> float:
    """RF-LSCM's share of the demo's budget: what is left of it, at least ``MIN_RFLSCM_S`` (with a warning)."""
    if left_s >= MIN_RFLSCM_S:
        return left_s
    console.print(
        f"[yellow]note:[/yellow] WNOMP left {max(left_s, 0.0):.0f} s of the budget; RF-LSCM gets {MIN_RFLSCM_S:g} s "
        "and the demo will run over (give more `--minutes`)."
    )
    return MIN_RFLSCM_S


OVER_NOTE = 0.02
"""The demo notes how its time went when it ends more than this share past its budget."""


def overrun_note(elapsed_s: float, budget_s: float, parts: dict[str, float]) -> str | None:
    """A note when the demo took more than ``OVER_NOTE`` past its ``budget_s``: how long it took, where the time went
    (``parts``: seconds per stage) and the ``--minutes`` that would hold it; None within the budget.  It runs over
    only where WNOMP, RF-LSCM's least pass (the levels and WNOMP's APS of every training pair) and RF-LSCM's
    evaluation leave its training less than its least share, which a larger network's first minutes can."""
    if elapsed_s <= (1.0 + OVER_NOTE) * budget_s:
        return None
    split = ", ".join(f"{name} {seconds:.0f} s" for name, seconds in parts.items())
    enough = math.ceil((1.0 + OVER_NOTE) * elapsed_s / 60.0)
    return (
        f"[yellow]note:[/yellow] the demo took {elapsed_s / 60:.1f} min of its {budget_s / 60:g}-minute budget ({split}): "
        f"this network's least work does not fit it; give `--minutes {enough}` or more for the budget to hold."
    )


@app.command()
def demo(
    out: Path = typer.Option(
        Path("rflscm-demo"), "--out", help="Folder for checkpoints, metrics JSON, the comparison table and reports."
    ),
    scenario: Path | None = typer.Option(
        None, "--scenario", help="Scenario folder (default: the shipped munich scenario)."
    ),
    config: str = typer.Option(
        "quick",
        "--config",
        help="RF-LSCM preset (quick, full) or a YAML file of the settings that differ from --preset.",
    ),
    preset: str | None = PresetOption,
    sets: list[str] = SetOption,
    minutes: float = typer.Option(
        DEMO_MINUTES,
        "--minutes",
        help="The whole demo's budget (min): WNOMP goes first; RF-LSCM trains in what is left after the time kept "
        "for its pass after training, its evaluation and reports.",
    ),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show progress bars."),
    device: Device = DeviceOption,
    seed: int = SeedOption,
    force: bool = ForceOption,
) -> None:
    """Train WNOMP (settings chosen on held-aside round-1 beams) and RF-LSCM on the shipped scenario, print the
    antenna-adjustment MAE table beside both floors and the trivial baseline, save it (comparison.md, .csv, .json)
    and write reports."""
    from rflscm.cli.train import config_inputs
    from rflscm.data import load_scenario, write_table
    from rflscm.data.loader import scenario_inputs
    from rflscm.data.safe_io import guard_outputs, write_text_atomic
    from rflscm.eval import run_evaluation
    from rflscm.eval.evaluate import tested_pairs
    from rflscm.eval.protocols import AdjustProtocol, fit_with_protocol
    from rflscm.eval.report import write_report
    from rflscm.geometry import AngleGrid
    from rflscm.models import MODEL_REGISTRY
    from rflscm.sim import default_scenario_path

    check_numbers(seed=(seed, 0, SEED_MAX))
    inputs = [*(scenario_inputs(scenario) if scenario is not None else []), *config_inputs(config)]
    guard_outputs({"--out": out}, inputs, force=True, folders=("--out",))
    names = [
        "wnomp_selection.csv",
        "wnomp.ckpt",
        "rflscm.ckpt",
        "wnomp.json",
        "rflscm.json",
        "comparison.md",
        "comparison.csv",
        "comparison.json",
    ]
    guard_outputs({f"--out (its {n})": out / n for n in names}, inputs, force=force)
    console = Console()
    started = command_start()
    budget_s = budget_seconds(minutes)
    assert budget_s is not None
    rflscm_cfg = model_config("rflscm", config, preset, sets)  # a wrong key stops the demo before any work
    dev = resolve_device(device)
    scen = load_scenario(scenario or default_scenario_path())
    output_folder(out, "--out")
    console.print(
        f"scenario [bold]{scen.meta.name}[/bold]: {len(scen.cell_ids())} cells, {len(scen.grid_ids())} grids; device {dev}"
    )
    console.print(f"budget: {minutes:g} min in all (--minutes); RF-LSCM trains in what WNOMP leaves")
    results: dict[str, dict] = {}
    from rflscm.models.wnomp_select import select_wnomp

    with console.status("choosing WNOMP's settings on held-aside round-1 beams…"):
        wnomp_cfg, choice = select_wnomp(scen, AngleGrid(), seed=seed, device=str(dev))
    write_table(choice, out / "wnomp_selection.csv")
    console.print(
        f"WNOMP settings chosen on held-aside round-1 beams ({int(choice['beams'].iloc[0])} beams): "
        f"k_max {wnomp_cfg.k_max}, weighting {wnomp_cfg.weighting}, tolerance {wnomp_cfg.tolerance}, "
        f"residual floor {wnomp_cfg.residual_floor} (all candidates: {out / 'wnomp_selection.csv'})"
    )
    from rflscm.config import to_dict

    # the pairs RF-LSCM's pass does not reach within the budget get WNOMP's APS of their reports with the baseline's
    # selected settings, as the baseline answers them (a YAML or --set of corrections.wnomp_fallback still wins)
    rflscm_cfg = model_config(
        "rflscm", config, preset, sets, under={"corrections": {"wnomp_fallback": to_dict(wnomp_cfg)}}
    )
    configs: dict[str, str | dict[str, Any]] = {"wnomp": to_dict(wnomp_cfg), "rflscm": rflscm_cfg}
    # RF-LSCM's evaluation renders the test pairs without a round-1 report (their time measured on a chunk of them);
    # its pass renders (or answers with WNOMP's APS) every pair with one, where a fit told of them renders those it
    # leaves itself
    known, fresh = tested_pairs(scen, AdjustProtocol())
    after_s = 0.0  # what WNOMP's save, evaluation and report took: RF-LSCM's take as long besides its renders
    parts: dict[str, float] = {}  # seconds per stage, for the note of a demo past its budget
    for name, model_cfg in configs.items():
        seed_everything(seed)
        model = MODEL_REGISTRY[name].build(model_cfg, AngleGrid(), dev)
        console.print(f"training [bold]{name}[/bold]…")
        t0 = time.perf_counter()
        budget = rflscm_budget(budget_s - (t0 - started), console) if name == "rflscm" else None
        summary = fit_with_protocol(
            model,
            scen,
            AdjustProtocol(),
            progress=progress,
            budget_s=budget,
            after_pairs=known,
            after_fresh=fresh,
            after_s=after_s,
        )
        model.run_info["fit"] = {**{k: float(v) for k, v in summary.items()}, "train_time_s": time.perf_counter() - t0}
        if (line := budget_summary(summary)) is not None:
            console.print(line)
        if (note := budget_note(summary)) is not None:
            console.print(note)
        t0 = time.perf_counter()
        model.save(out / f"{name}.ckpt")
        console.print(f"evaluating {name}…")
        evaluation = run_evaluation(model, scen, AdjustProtocol(), oracle="auto", progress=progress)
        metrics = evaluation.metrics
        write_text_atomic(out / f"{name}.json", json_text(metrics), "metrics JSON")
        write_report(evaluation, scen, model, out / f"report-{name}")
        results[name] = metrics
        after_s = time.perf_counter() - t0
        if name == "rflscm":
            parts["RF-LSCM's fit"] = model.run_info["fit"]["train_time_s"]
            kept = model.run_info["fit"].get("after_kept_s")
            parts["its evaluation and reports" + ("" if kept is None else f" (kept for them: {kept:.0f} s)")] = after_s
        else:
            parts["loading and WNOMP"] = time.perf_counter() - started
    title = f"Antenna adjustment on {scen.meta.name}: round-2 RSRP predicted from round 1"
    console.print(demo_table(results, title))
    saved = save_comparison(results, title, out)
    console.print(f"comparison table: {', '.join(str(p) for p in saved)}")
    console.print(f"reports: {out / 'report-rflscm' / 'report.md'}, {out / 'report-wnomp' / 'report.md'}")
    if (note := overrun_note(time.perf_counter() - started, budget_s, parts)) is not None:
        console.print(note)
