"""``rflscm evaluate CHECKPOINT SCENARIO``: accuracy metrics as a table, JSON and a report."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console
from rich.markup import escape
from rich.table import Table

from rflscm.cli import app
from rflscm.cli.common import (
    Device,
    DeviceOption,
    ForceOption,
    SeedOption,
    json_text,
    resolve_device,
    seed_everything,
)
from rflscm.cli.train import Protocol
from rflscm.errors import ConfigError
from rflscm.parallel import Engine, RayAddressOption, WorkersOption


@app.command()
def evaluate(
    checkpoint: Path = typer.Argument(..., help="Model checkpoint written by `rflscm train`."),
    scenario: Path = typer.Argument(..., help="The scenario folder the model was trained on."),
    protocol_choice: Protocol | None = typer.Option(
        None, "--protocol", help="adjust, unseen or multifreq (default: the one the checkpoint was trained for)."
    ),
    json_out: Path | None = typer.Option(None, "--json", help="Write the metrics as JSON to this file."),
    report: Path | None = typer.Option(
        None, "--report", help="Write report.md and PNG figures (maps, error CDFs) into this folder."
    ),
    oracle: bool = typer.Option(
        True, "--oracle/--no-oracle", help="Compute the oracle floor where ground truth exists."
    ),
    progress: bool = typer.Option(
        True, "--progress/--no-progress", help="Show a progress bar over the cells, with its ETA (on a terminal)."
    ),
    device: Device = DeviceOption,
    seed: int = SeedOption,
    workers: int = WorkersOption,
    ray_address: str | None = RayAddressOption,
    force: bool = ForceOption,
) -> None:
    """Compare a trained model's predictions with measurements: MAE per beam type, changed cells, per cell,
    beside the oracle floor and the trivial baseline; APS recovery where ground truth exists."""
    protocol = None if protocol_choice is None else protocol_choice.value
    from rflscm.data import load_scenario
    from rflscm.eval import PROTOCOLS, resolve_protocol, run_evaluation
    from rflscm.eval.report import metric_rows, write_report
    from rflscm.models import load_model
    from rflscm.parallel.aps import checkpoint_loader, evaluation_cache

    if protocol is not None and protocol not in PROTOCOLS:
        raise ConfigError(f"--protocol {protocol!r} is unknown; choose one of: {', '.join(PROTOCOLS)}.")
    from rflscm.data.loader import scenario_inputs
    from rflscm.data.safe_io import guard_outputs, write_text_atomic

    if json_out is not None and json_out.suffix.lower() != ".json":
        raise ConfigError(f"--json {json_out}: the file name must end in .json.")
    inputs = [*scenario_inputs(scenario), checkpoint]
    guard_outputs({"--json": json_out, "--report": report}, inputs, force=force, folders=("--report",))
    seed_everything(seed)
    dev = resolve_device(device)
    sc = load_scenario(scenario)
    model = load_model(checkpoint, sc, device=dev)
    chosen = resolve_protocol(model, protocol)
    engine = Engine(workers, ray_address)  # > 1 worker: the test pairs' APS are computed by Ray workers first
    source = evaluation_cache(model, sc, chosen, engine, checkpoint_loader(checkpoint, scenario, dev))
    console = Console()
    if model.run_info.get("interrupted"):
        console.print(
            "[yellow]note:[/yellow] this checkpoint was saved by a training run that was interrupted (or is still "
            "running); it is not fully trained — continue it with `rflscm train … --resume`."
        )
    console.print(f"evaluating {model.name} ({chosen.name} protocol) on {len(sc.cell_ids())} cells…")
    evaluation = run_evaluation(source, sc, chosen, oracle="auto" if oracle else None, progress=progress)
    metrics = evaluation.metrics
    table = Table(title=f"{model.name} on {sc.meta.name} — {chosen.name} protocol, round {metrics['test_round']}")
    table.add_column("metric", justify="left")
    for column in ("model", "oracle", "trivial"):
        table.add_column(column, justify="right")
    for row in metric_rows(metrics):
        table.add_row(*(escape(cell) for cell in row))
    console.print(table)
    if metrics["unsupported"]:
        console.print(f"[yellow]note:[/yellow] {escape(metrics['unsupported'])}")
    if json_out is not None:
        write_text_atomic(json_out, json_text(metrics), "metrics JSON")
        console.print(f"wrote {json_out}")
    if report is not None:
        path = write_report(evaluation, sc, model, report)
        console.print(f"wrote {path}")
