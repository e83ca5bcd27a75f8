"""``rflscm map``: GeoTIFF, GeoJSON, KML and an offline HTML map of a trained model's predicted KPIs."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.console import Console

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


@app.command("map")
def map_(
    checkpoint: Path = typer.Argument(..., help="Model checkpoint written by `rflscm train`."),
    scenario: Path = typer.Argument(..., help="The scenario the model was trained on."),
    round: int = typer.Option(1, "--round", help="Round whose antenna configuration to map (integer)."),
    compare_round: int | None = typer.Option(
        None,
        "--compare-round",
        metavar="M",
        help="A second round (integer): its layers too, and the difference (round M − --round).",
    ),
    out: Path = typer.Option(Path("maps"), "--out", help="Output folder: GeoTIFF, GeoJSON, KML and HTML files."),
    threshold: float = typer.Option(-105.0, "--threshold", help="Coverage threshold on best-server SSB RSRP (dBm)."),
    noise_figure: float = typer.Option(7.0, "--noise-figure", help="UE noise figure for SS-SINR (dB)."),
    html: bool = typer.Option(True, "--html/--no-html", help="Also write the interactive map, map.html."),
    device: Device = DeviceOption,
    seed: int = SeedOption,
    force: bool = ForceOption,
) -> None:
    """Write map layers of predicted best-server RSRP, serving cell, SS-SINR and coverage (docs/maps.md)."""
    from rflscm.data import load_scenario
    from rflscm.data.loader import scenario_inputs
    from rflscm.data.safe_io import guard_outputs
    from rflscm.maps import write_layers
    from rflscm.models import load_model
    from rflscm.network.kpi import KPIConfig

    check_numbers(
        round=(round, 1, 2**31 - 1),
        compare_round=(compare_round, 1, 2**31 - 1),
        threshold=(threshold, -300.0, 100.0),
        noise_figure=(noise_figure, 0.0, 30.0),
        seed=(seed, 0, SEED_MAX),
    )
    guard_outputs({"--out": out}, [*scenario_inputs(scenario), checkpoint], force=force, folders=("--out",))
    seed_everything(seed)
    console = Console(stderr=True)
    scen = load_scenario(scenario)
    kpi = KPIConfig(threshold_dbm=threshold, noise_figure_db=noise_figure)
    model = load_model(checkpoint, scen, device=resolve_device(device))
    with console.status(f"predicting and drawing with {model.name}…"):
        result = write_layers(model, scen, out, round, compare_round, kpi, html=html)
    console.print(f"KPIs on {result.layers[0].pairs}; {result.frame.note}")
    for path in result.files:
        console.print(f"wrote {path}")
