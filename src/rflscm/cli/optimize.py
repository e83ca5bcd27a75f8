"""``rflscm optimize``: search antenna tilts, azimuths and SSB codebooks on a trained model."""

from __future__ import annotations

import sys
from pathlib import Path

import typer
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
)

from rflscm.cli import app
from rflscm.cli.common import DeviceOption, SeedOption, resolve_device, seed_everything
from rflscm.errors import ConfigError
from rflscm.parallel import Engine, RayAddressOption, WorkersOption


def search_spec(search: Path | None, tilt: str | None, elec: str | None, azimuth: str | None, codebooks: str | None,
                freeze: str | None, max_changed: int | None) -> dict:  # fmt: skip
    """The search spec: the YAML file's, with CLI flags laid over its ``defaults``."""
    from rflscm.network.space import load_spec, parse_range

    spec = load_spec(search)
    defaults = dict(spec.get("defaults") or {})
    for flag, key, text in (("--tilt-range", "mech_tilt_deg", tilt), ("--elec-tilt-range", "elec_tilt_deg", elec),
                            ("--azimuth-range", "azimuth_offset_deg", azimuth)):  # fmt: skip
        if text is not None:
            defaults[key] = parse_range(text, flag)
    if codebooks is not None:
        defaults["ssb_codebooks"] = [c.strip() for c in codebooks.split(",") if c.strip()]
    spec["defaults"] = defaults
    if freeze is not None:
        try:
            spec["frozen"] = [int(v) for v in freeze.split(",") if v.strip()]
        except ValueError:
            raise ConfigError(f"--freeze takes comma-separated cell ids (got {freeze!r}).") from None
    if max_changed is not None:
        spec["max_changed_cells"] = max_changed
    return spec


@app.command()
def optimize(
    checkpoint: Path = typer.Argument(..., help="Model checkpoint written by `rflscm train`."),
    scenario: Path = typer.Argument(..., help="The scenario the model was trained on."),
    objective: str = typer.Option("coverage", "--objective", help="coverage, sinr or weighted."),
    out: Path = typer.Option(Path("optimize-out"), "--out", help="Output folder: new round, changes, report."),
    search: Path | None = typer.Option(None, "--search", help="YAML search spec (defaults, per-cell ranges, frozen)."),
    tilt_range: str | None = typer.Option(None, "--tilt-range", help="Mechanical tilt MIN:MAX[:STEP] [deg] (0:15:1)."),
    elec_range: str | None = typer.Option(None, "--elec-tilt-range", help="Electrical tilt MIN:MAX[:STEP] (0:15:1)."),
    azimuth_range: str | None = typer.Option(
        None, "--azimuth-range", help="Azimuth offsets MIN:MAX[:STEP] (-30:30:5)."
    ),
    codebooks: str | None = typer.Option(None, "--codebooks", help="Comma-separated SSB codebooks (default: all)."),
    freeze: str | None = typer.Option(None, "--freeze", help="Comma-separated cell ids that must not change."),
    max_changed: int | None = typer.Option(None, "--max-changed", help="Most cells the recommendation may change."),
    base_round: int = typer.Option(1, "--round", help="Configuration the search starts from."),
    method: str = typer.Option("cd", "--method", help="cd (coordinate descent + restarts) or de (scipy DE)."),
    restarts: int = typer.Option(2, "--restarts", min=0, help="cd: restarts from perturbed best configurations."),
    time_budget: float = typer.Option(60.0, "--time-budget", help="de: seconds of search."),
    threshold: float = typer.Option(-105.0, "--threshold", help="Coverage threshold on best-server RSRP [dBm]."),
    noise_figure: float = typer.Option(7.0, "--noise-figure", help="UE noise figure [dB] for SS-SINR."),
    verify: bool | None = typer.Option(
        None,
        "--verify/--no-verify",
        help="True KPIs from truth/ (default: if present).",
    ),
    aps_cache: Path | None = typer.Option(None, "--aps-cache", help="Reuse/write the rendered APS here (.pt)."),
    device: str = DeviceOption,
    seed: int = SeedOption,
    workers: int = WorkersOption,
    ray_address: str | None = RayAddressOption,
) -> None:
    """Search antenna settings that maximise a coverage/SINR objective; write them as a new round."""
    from rflscm.data import load_scenario
    from rflscm.models import load_model
    from rflscm.models.source import APSSource
    from rflscm.network.kpi import KPIConfig
    from rflscm.network.optimize import load_or_cache_aps, run_optimize, write_round
    from rflscm.network.report import write_report
    from rflscm.network.space import build_space

    seed_everything(seed)
    console = Console(stderr=True)
    scen = load_scenario(scenario)
    if base_round not in scen.cells:
        raise ConfigError(
            f"--round {base_round}: scenario {scen.meta.name!r} has rounds {', '.join(map(str, scen.rounds()))}."
        )
    kpi = KPIConfig(threshold_dbm=threshold, noise_figure_db=noise_figure)
    spec = search_spec(search, tilt_range, elec_range, azimuth_range, codebooks, freeze, max_changed)
    space = build_space(spec, scen.cells[base_round], scen.meta.codebooks)
    if verify:
        from rflscm.sim.truth import truth_folder

        truth_folder(scen)  # fail before the expensive part
    model = load_model(checkpoint, scen, device=resolve_device(device))
    source: APSSource = model  # > 1 worker: the APS to render are computed by Ray workers first
    if aps_cache is None or not aps_cache.exists():
        from rflscm.parallel.aps import checkpoint_loader, render_cache

        load = checkpoint_loader(checkpoint, scenario, model.device)
        source = render_cache(model, scen, Engine(workers, ray_address), load)
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
    )
    with Progress(*columns, console=console, transient=True) as bar:
        task = bar.add_task(f"rendering APS ({model.name})", total=len(scen.cell_ids()))
        cache, cache_s = load_or_cache_aps(
            source,
            scen,
            aps_cache,
            on_cell=lambda done, _: bar.update(task, completed=done),
        )
        passes = (restarts + 1) * 8 * len(space.free_cells()) if method == "cd" else None
        task = bar.add_task(f"searching ({method}, {objective})", total=passes)
        result = run_optimize(scen, cache, space, base_round, objective, method, kpi, verify, seed, restarts,
                              time_budget, on_step=lambda: bar.advance(task))  # fmt: skip
    result.timings["aps_cache_s"] = cache_s
    folder, rnd = write_round(scen, result.cells_after, out)
    report = write_report(result, scen, out, kpi, rnd, folder, command="rflscm " + " ".join(sys.argv[1:]))
    _print(console, result, folder, rnd, report)


def _print(console: Console, result, folder: Path, rnd: int, report: Path) -> None:
    from rich.table import Table

    s = result.summary()
    if result.known is not None:
        console.print(
            f"[yellow]note:[/yellow] {result.model} has APS for measured pairs only; predicted KPIs use those."
        )
    table = Table(title=f"{result.model}: {len(result.changes)} cells changed")
    for col in (
        "KPI",
        "pred. before",
        "pred. after",
        *(("true before", "true after") if result.truth else ()),
    ):
        table.add_column(col, justify="right")
    for key in ("coverage", "mean_sinr_db", "p5_sinr_db", "overlap", "mean_rsrp_dbm"):
        row = [
            key,
            f"{s['predicted']['before'][key]:.4g}",
            f"{s['predicted']['after'][key]:.4g}",
        ]
        if result.truth:
            row += [
                f"{s['truth']['before'][key]:.4g}",
                f"{s['truth']['after'][key]:.4g}",
            ]
        table.add_row(*row)
    console.print(table)
    console.print(f"wrote round {rnd} to {folder / 'scenario.yaml'}, report {report}")
