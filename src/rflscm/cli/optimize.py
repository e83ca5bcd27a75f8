"""``rflscm optimize``: search antenna tilts, azimuths and SSB codebooks on a trained model."""

from __future__ import annotations

import math
import sys
from collections.abc import Iterable
from enum import StrEnum
from pathlib import Path

import typer
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)

from rflscm.cli import app
from rflscm.cli.common import (
    SEED_MAX,
    Device,
    DeviceOption,
    ForceOption,
    SeedOption,
    check_numbers,
    resolve_device,
    seed_everything,
)
from rflscm.errors import ConfigError
from rflscm.parallel import Engine, RayAddressOption, WorkersOption


class Objective(StrEnum):
    coverage = "coverage"
    sinr = "sinr"
    weighted = "weighted"


class Pairs(StrEnum):
    reach = "reach"
    measured = "measured"


class Method(StrEnum):
    cd = "cd"
    de = "de"


def search_spec(
    search: Path | None,
    tilt: str | None,
    elec: str | None,
    azimuth: str | None,
    codebooks: str | None,
    freeze: str | None,
    max_changed: int | None,
    cells: str | None = None,
    cell_ids: Iterable[int] | None = None,
) -> dict:
    """The search spec: the YAML file's, with CLI flags laid over its ``defaults``; ``cells`` (``--cells``)
    freezes every cell of ``cell_ids`` but these."""
    from rflscm.network.space import check_physical, load_spec, parse_range

    spec = load_spec(search)
    defaults = dict(spec.get("defaults") or {})
    for flag, key, text in (
        ("--tilt-range", "mech_tilt_deg", tilt),
        ("--elec-tilt-range", "elec_tilt_deg", elec),
        ("--azimuth-range", "azimuth_offset_deg", azimuth),
    ):
        if text is not None:
            defaults[key] = parse_range(text, flag)
            check_physical(key, defaults[key]["min"], defaults[key]["max"], flag)
    if codebooks is not None:
        defaults["ssb_codebooks"] = [c.strip() for c in codebooks.split(",") if c.strip()]
    spec["defaults"] = defaults
    check_ranges(spec, "search spec")
    if freeze is not None:
        try:
            spec["frozen"] = [int(v) for v in freeze.split(",") if v.strip()]
        except ValueError:
            raise ConfigError(f"--freeze takes comma-separated cell ids (got {freeze!r}).") from None
    if cells is not None:
        try:
            only = {int(v) for v in cells.split(",") if v.strip()}
        except ValueError:
            raise ConfigError(f"--cells takes comma-separated cell ids (got {cells!r}).") from None
        known = {int(c) for c in (cell_ids if cell_ids is not None else [])}
        unknown = sorted(only - known)
        if not only or unknown:
            raise ConfigError(f"--cells {cells}: no such cell(s) {', '.join(map(str, unknown)) or '(none given)'}.")
        spec["frozen"] = sorted({*(int(c) for c in spec.get("frozen") or []), *(known - only)})
    if max_changed is not None:
        spec["max_changed_cells"] = max_changed
    return spec


MAX_RANGE_POINTS = 100_000
"""The most values one searched range (MIN:MAX:STEP) may hold."""


def check_ranges(value: object, where: str) -> None:
    """Every range (a mapping with ``min`` and ``max``) in a search spec: finite numbers, a positive step and at most
    :data:`MAX_RANGE_POINTS` values, checked before any search space is built."""
    if isinstance(value, dict):
        if "min" in value and "max" in value:
            low, high, step = value.get("min"), value.get("max"), value.get("step", 1.0)
            try:
                numbers = [float(v) for v in (low, high, step)]  # type: ignore[arg-type]
            except (TypeError, ValueError, OverflowError):
                return  # not numbers: build_space names the key
            if not all(math.isfinite(v) for v in numbers):
                raise ConfigError(f"{where}: a range {low}:{high}:{step} must be finite numbers of degrees.")
            if numbers[2] <= 0:
                raise ConfigError(f"{where}: the step of the range {low}:{high}:{step} must be positive.")
            points = abs(numbers[1] - numbers[0]) / numbers[2] + 1
            if points > MAX_RANGE_POINTS:
                raise ConfigError(
                    f"{where}: the range {low}:{high}:{step} holds {points:.3g} values, above the limit of "
                    f"{MAX_RANGE_POINTS:,}; use a larger step."
                )
        for key, item in value.items():
            check_ranges(item, f"{where}: {key}")
    elif isinstance(value, list):
        for item in value:
            check_ranges(item, where)


@app.command()
def optimize(
    checkpoint: Path = typer.Argument(..., help="Model checkpoint written by `rflscm train`."),
    scenario: Path = typer.Argument(..., help="The scenario folder the model was trained on."),
    objective: Objective = typer.Option(
        Objective.coverage,
        "--objective",
        help="What to maximise: coverage ratio (%), mean SS-SINR (dB) or weighted (1 dB of SINR = 1 % coverage).",
    ),
    out: Path = typer.Option(Path("optimize-out"), "--out", help="Output folder: new round, changes, report."),
    search: Path | None = typer.Option(
        None, "--search", help="YAML search spec: ranges (deg), per-cell overrides, frozen cells, step limits."
    ),
    tilt_range: str | None = typer.Option(
        None,
        "--tilt-range",
        metavar="MIN:MAX[:STEP]",
        help="Mechanical down-tilt range (deg), within -10:20 (default 0:15:1, at most ±4 per step).",
    ),
    elec_range: str | None = typer.Option(
        None,
        "--elec-tilt-range",
        metavar="MIN:MAX[:STEP]",
        help="Electrical down-tilt range (deg), within -5:20 (default 0:15:1, at most ±4 per step).",
    ),
    azimuth_range: str | None = typer.Option(
        None,
        "--azimuth-range",
        metavar="MIN:MAX[:STEP]",
        help="Azimuth offsets around the present azimuth (deg, clockwise), within -60:60 (default -30:30:5, "
        "at most ±10 per step).",
    ),
    codebooks: str | None = typer.Option(
        None, "--codebooks", metavar="NAMES", help="Comma-separated SSB codebooks of scenario.yaml (default: all)."
    ),
    cells: str | None = typer.Option(
        None,
        "--cells",
        metavar="IDS",
        help="Comma-separated cell ids that may change (the others are frozen); the APS are rendered only "
        "at the grids these cells reach, and the KPIs are those grids' (a cluster of a large network).",
    ),
    pairs: Pairs = typer.Option(
        Pairs.reach,
        "--pairs",
        help="Pairs the APS are rendered and the KPIs computed on: reach (every grid within the model's reach of "
        "a cell; WNOMP: its measured pairs) or measured (round-1 measured pairs only, fewer to render).",
    ),
    freeze: str | None = typer.Option(
        None, "--freeze", metavar="IDS", help="Comma-separated cell ids that must not change."
    ),
    max_changed: int | None = typer.Option(
        None,
        "--max-changed",
        min=1,
        metavar="N",
        help="Most cells the recommendation may change (cells; default 8).",
    ),
    base_round: int = typer.Option(
        1, "--round", help="Round the search starts from (integer; its antenna configuration)."
    ),
    method: Method = typer.Option(
        Method.cd, "--method", help="cd: coordinate descent with restarts; de: scipy's differential evolution."
    ),
    restarts: int = typer.Option(
        2, "--restarts", min=0, help="cd: restarts from perturbed best configurations (count)."
    ),
    time_budget: float = typer.Option(60.0, "--time-budget", help="de: search time (s)."),
    threshold: float = typer.Option(-105.0, "--threshold", help="Coverage threshold on best-server SSB RSRP (dBm)."),
    noise_figure: float = typer.Option(7.0, "--noise-figure", help="UE noise figure for SS-SINR (dB)."),
    verify: bool | None = typer.Option(
        None,
        "--verify/--no-verify",
        help="True KPIs from truth/ (default: if the scenario has it).",
    ),
    aps_cache: Path | None = typer.Option(None, "--aps-cache", help="Reuse or write the rendered APS here (.pt file)."),
    maps: bool = typer.Option(
        False, "--maps", help="Also write map layers before/after (GeoTIFF, GeoJSON, KML, HTML) into OUT/maps."
    ),
    device: Device = DeviceOption,
    seed: int = SeedOption,
    workers: int = WorkersOption,
    ray_address: str | None = RayAddressOption,
    force: bool = ForceOption,
) -> None:
    """Search antenna settings that maximise a coverage/SINR objective; write them as a new round."""
    from rflscm.data import load_scenario
    from rflscm.data.loader import scenario_inputs
    from rflscm.data.safe_io import guard_outputs
    from rflscm.models import load_model
    from rflscm.models.source import APSSource
    from rflscm.network.kpi import KPIConfig
    from rflscm.network.optimize import load_or_cache_aps, run_optimize, write_round
    from rflscm.network.report import write_report
    from rflscm.network.space import build_space

    check_numbers(
        round=(base_round, 1, 2**31 - 1),
        restarts=(restarts, 0, 1000),
        time_budget=(time_budget, 0.0, 1e7),
        threshold=(threshold, -300.0, 100.0),
        noise_figure=(noise_figure, -50.0, 100.0),
        max_changed=(max_changed, 1, 2**31 - 1),
        seed=(seed, 0, SEED_MAX),
    )
    if aps_cache is not None and aps_cache.suffix.lower() != ".pt":
        raise ConfigError(f"--aps-cache {aps_cache}: the file name must end in .pt.")
    inputs = [*scenario_inputs(scenario), checkpoint, search]
    guard_outputs({"--out": out}, inputs, force=force, folders=("--out",))
    written = {"--out (its scenario.yaml)": out / "scenario" / "scenario.yaml", "--out (its report)": out / "report.md"}
    guard_outputs(written, [*inputs, aps_cache], force=force)
    if aps_cache is not None:  # read when it fits the checkpoint, else written: never one of the other inputs
        guard_outputs({"--aps-cache": aps_cache}, inputs, force=True)
    seed_everything(seed)
    console = Console(stderr=True)
    scen = load_scenario(scenario)
    if base_round not in scen.cells:
        raise ConfigError(
            f"--round {base_round}: scenario {scen.meta.name!r} has rounds {', '.join(map(str, scen.rounds()))}."
        )
    kpi = KPIConfig(threshold_dbm=threshold, noise_figure_db=noise_figure)
    spec = search_spec(
        search, tilt_range, elec_range, azimuth_range, codebooks, freeze, max_changed, cells, scen.cell_ids()
    )
    space = build_space(spec, scen.cells[base_round], scen.meta.codebooks)
    free_cells = scen.cell_ids()[space.free_cells()]
    if verify:
        from rflscm.sim.truth import truth_folder

        truth_folder(scen)  # fail before the expensive part
    model = load_model(checkpoint, scen, device=resolve_device(device.value))
    objective_name, method_name = objective.value, method.value
    source: APSSource = model  # > 1 worker: the APS to render are computed by Ray workers first
    if aps_cache is None or not aps_cache.exists():
        from rflscm.parallel.aps import checkpoint_loader, render_cache

        console.print(_render_note(model, scen, free_cells, pairs == Pairs.measured))

        load = checkpoint_loader(checkpoint, scenario, model.device)
        source = render_cache(model, scen, Engine(workers, ray_address), load, free_cells, pairs == Pairs.measured)
    columns = (
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        TimeRemainingColumn(),  # the ETA; the search's total is an upper bound (passes stop when none improves)
    )
    with Progress(*columns, console=console, transient=True) as bar:
        task = bar.add_task(f"rendering APS ({model.name})", total=len(scen.cell_ids()))
        cache, cache_s = load_or_cache_aps(
            source,
            scen,
            aps_cache,
            on_cell=lambda done, _: bar.update(task, completed=done),
            free_cells=free_cells,
            measured=pairs == Pairs.measured,
        )
        passes = (restarts + 1) * 8 * len(space.free_cells()) if method_name == "cd" else None
        task = bar.add_task(f"searching ({method_name}, {objective_name})", total=passes)
        result = run_optimize(
            scen,
            cache,
            space,
            base_round,
            objective_name,
            method_name,
            kpi,
            verify,
            seed,
            restarts,
            time_budget,
            on_step=lambda: bar.advance(task),
        )
    result.timings["aps_cache_s"] = cache_s
    folder, rnd = write_round(scen, result.cells_after, out)
    report = write_report(result, scen, out, kpi, rnd, folder, command="rflscm " + " ".join(sys.argv[1:]))
    _print(console, result, folder, rnd, report)
    if maps:
        from rflscm.maps import write_layers

        with console.status("writing map layers before/after…"):
            layers = write_layers(model, load_scenario(folder), out / "maps", base_round, rnd, kpi)
        console.print(f"wrote {len(layers.files)} map files to {out / 'maps'} (docs/maps.md)")


def _render_note(model, scen, free_cells, measured: bool) -> str:
    """What the APS cache will render, in one line: its (cell, grid) pairs, and the measured ones among them when
    ``--pairs reach`` asks for more (a large network's cluster can reach most of its grids)."""
    from rflscm.eval.cache import render_rows

    count = sum(len(r) for r in render_rows(model, scen, free_cells, measured))
    note = f"rendering the APS of {count:,} (cell, grid) pairs"
    if not measured and model.supports_unseen_grids:
        fewer = sum(len(r) for r in render_rows(model, scen, free_cells, True))
        if fewer < count:
            note += f" ({fewer:,} with --pairs measured)"
    return note


def _print(console: Console, result, folder: Path, rnd: int, report: Path) -> None:
    from rich.markup import escape
    from rich.table import Table

    from rflscm.network.report import KPI_ROWS

    s = result.summary()
    pairs = f"{s['kpi_pairs']}, {s['kpi_pair_count']} (cell, grid) pairs"
    table = Table(title=f"{result.model}: {len(result.changes)} cells changed; KPIs on {pairs}, predicted and true")
    columns = ["KPI", "pred. before", "pred. after", "pred. gain"]
    if result.truth is not None:
        columns += ["true before", "true after", "true gain"]
    if result.held_out is not None:
        columns += ["held-out pred. gain"]
    table.add_column(columns[0], justify="left", no_wrap=True)
    for col in columns[1:]:
        table.add_column(col, justify="right")
    for key, label, scale, unit in KPI_ROWS:
        row = [f"{label} ({unit})"]
        for kpis in (s["predicted"], s.get("truth")):
            if kpis is not None:
                b, a = kpis["before"][key] * scale, kpis["after"][key] * scale
                row += [f"{b:.2f}", f"{a:.2f}", f"{a - b:+.2f}"]
        if result.held_out is not None:
            row.append(f"{s['held_out_gain'][key] * scale:+.2f}")
        table.add_row(*row)
    console.print(table)
    v = s["verdict"]
    if v["flagged"]:
        console.print(f"[bold red]warning: {escape(v['text'])}.[/bold red]")
    elif v["basis"] is not None:
        console.print(f"check passed: {escape(v['text'])}.")
    console.print(f"wrote round {rnd} to {folder / 'scenario.yaml'}, report {report}")
