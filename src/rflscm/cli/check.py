"""``rflscm check SCENARIO``: validate a scenario folder and print what it holds."""

from __future__ import annotations

import os
from pathlib import Path

import typer
from rich.console import Console
from rich.table import Table

from rflscm.cli import app
from rflscm.data import ASPRS_CLASSES, Scenario, load_scenario
from rflscm.data.summary import cells_per_carrier, measurement_stats, notes, table_rows


@app.command()
def check(
    scenario: Path = typer.Argument(..., help="Scenario folder (with scenario.yaml) or its YAML file."),
) -> None:
    """Validate a scenario (every file, row and column) and print a short summary.

    Exits 0 when valid; otherwise prints one line naming the file, row and column, and exits 2.
    """
    loaded = load_scenario(scenario)
    _print_summary(loaded, Console())


def files_read(sc: Scenario) -> list[str]:
    """Every file the scenario's loading read (symlinks resolved): scenario.yaml, its tables, the point cloud,
    the element pattern files of the cells tables; the truth folder is named, its files are read on demand."""
    from rflscm.data.cells import DEFAULT_ELEMENT
    from rflscm.data.loader import scenario_inputs

    paths = [p for p in scenario_inputs(sc.root) if p.exists()]
    names = {str(n) for t in sc.cells.values() if "element" in t.columns for n in t["element"].dropna().unique()}
    paths += [sc.root / n for n in sorted(names - {DEFAULT_ELEMENT, ""})]
    shown = []
    for path in dict.fromkeys(os.path.realpath(p) for p in paths):
        shown.append(path + ("/ (folder)" if os.path.isdir(path) else ""))
    return shown


def _ghz(freq_hz: float) -> str:
    return f"{freq_hz / 1e9:g} GHz"


def _print_summary(sc: Scenario, console: Console) -> None:
    meta = sc.meta
    console.print(f"[bold]{meta.name}[/bold]  ({sc.root})" + (f"\n  {meta.description}" if meta.description else ""))
    origin = "none (x/y/z in metres)" if meta.origin is None else f"{meta.origin.lat}, {meta.origin.lon}"
    console.print(f"  origin: {origin}   threshold: {meta.rsrp_threshold_dbm:g} dBm   rounds: {sc.rounds()}")
    ground = (
        f"{meta.terrain} (height_m is above ground)" if meta.terrain else "none (heights are absolute z / height_m)"
    )
    console.print(f"  terrain: {ground}")
    per_carrier = ", ".join(f"{_ghz(f)}: {n}" for f, n in cells_per_carrier(sc).items())
    sites = sc.cells[1]["site_id"].nunique()
    console.print(f"  cells: {len(sc.cell_ids())} on {sites} site(s) ({per_carrier})")
    console.print(f"  grids: {len(sc.grid_ids())}")
    books = ", ".join(f"{name} ({cb.type}, {cb.num_beams} beams)" for name, cb in meta.codebooks.items())
    console.print(f"  codebooks: {books}")
    rows = ", ".join(f"{name} {n:,}" for name, n in table_rows(sc).items())
    console.print(f"  rows read: {rows} (none rejected)", soft_wrap=True)
    console.print(f"  files read: {', '.join(files_read(sc))}", soft_wrap=True)
    _print_measurements(sc, console)
    _print_point_cloud(sc, console)
    for note in notes(sc):
        console.print(f"  [yellow]note:[/yellow] {note}")
    console.print(f"[green]OK[/green] fingerprint {sc.fingerprint()[:16]}")


def _print_measurements(sc: Scenario, console: Console) -> None:
    from rflscm.data.reporting import reported_fraction, rule_of, validate_reporting

    stats = measurement_stats(sc)
    if stats.empty:
        console.print("  measurements: none")
        return
    validate_reporting(sc)
    rules = "; ".join(f"{t}: {rule_of(sc, t).to_dict()}" for t in ("ssb", "csi"))
    console.print(f"  reporting rule: {rules}")
    table = Table(title=f"measurements ({len(sc.measurements):,} rows)", title_justify="left")
    for column in ("round", "beam", "rows", "cell–grid pairs", "cells", "grids", "missing"):
        table.add_column(column, justify="right")
    for row in stats.itertuples():
        counts = (f"{row.rows:,}", f"{row.pairs:,}", str(row.cells), str(row.grids))
        table.add_row(str(row.round), row.beam_type, *counts, f"{100 * row.missing:.1f} %")
    console.print(table)
    frac = reported_fraction(sc)
    text = ", ".join(f"round {r.round} {r.beam_type} {100 * r.fraction:.1f} %" for r in frac.itertuples())
    console.print(f"  reported fraction of the beams of detected (cell, grid) pairs: {text}")


def _print_point_cloud(sc: Scenario, console: Console) -> None:
    pc = sc.point_cloud
    if pc is None:
        console.print("  point cloud: none")
        console.print(
            "  [yellow]warning:[/yellow] the default RF-LSCM (`rflscm train --model rflscm`) needs a point cloud "
            "for its prior; add `point_cloud:` to scenario.yaml, or train with `--set prior.enabled=false`."
        )
        return
    classes = ", ".join(
        f"{ASPRS_CLASSES.get(c, f'class {c}')} {100 * n / pc.num_points:.0f} %" for c, n in pc.class_counts().items()
    )
    console.print(f"  point cloud: {pc.num_points:,} points ({classes})")
