"""``rflscm bench NAME``: run a benchmark, print its table, write JSON (+ plots)."""

from __future__ import annotations

import json
import platform
import subprocess
from datetime import UTC, datetime
from enum import StrEnum
from pathlib import Path
from typing import Any

import torch
import typer
from rich.console import Console
from rich.table import Table

from rflscm import __version__
from rflscm.bench import BENCHMARKS, BenchContext, load_all
from rflscm.cli import app
from rflscm.cli.common import Device, DeviceOption, SeedOption, resolve_device, seed_everything
from rflscm.errors import ConfigError


def _flatten(prefix: str, value: object, rows: list[tuple[str, str]]) -> None:
    if isinstance(value, dict):
        for k, v in value.items():
            _flatten(f"{prefix}.{k}" if prefix else str(k), v, rows)
    elif isinstance(value, float):
        rows.append((prefix, f"{value:.4g}"))
    elif isinstance(value, list) and len(value) > 8:
        rows.append((prefix, f"[{len(value)} values]"))
    else:
        rows.append((prefix, str(value)))


def _machine() -> dict[str, Any]:
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        commit = ""
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return {
        "date": datetime.now(UTC).strftime("%Y-%m-%d"),
        "commit": commit or "unknown",
        "rflscm": __version__,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "cpu_threads": torch.get_num_threads(),
        "gpu": gpu,
    }


class Size(StrEnum):
    quick = "quick"
    full = "full"


@app.command()
def bench(
    name: str = typer.Argument(..., help="Benchmark name; `rflscm bench list` shows them."),
    size_choice: Size = typer.Option(Size.quick, "--size", help="quick (2 CPU cores, minutes) or full (GPU)."),
    seeds: int = typer.Option(1, "--seeds", min=1, help="Seeds the benchmark repeats its runs over (count)."),
    out: Path = typer.Option(Path("bench-out"), "--out", help="Output folder for JSON and plots."),
    scenario: Path | None = typer.Option(None, "--scenario", help="Scenario folder (default: the shipped one)."),
    config: str | None = typer.Option(
        None,
        "--config",
        help="b9: the new RF-LSCM's preset or YAML file (default: the size's preset); b10: a YAML of its plan.",
    ),
    baseline: str | None = typer.Option(
        None,
        "--baseline",
        metavar="PATH",
        help="b9 (required), render (optional): folder holding the baseline code's exported src tree (a path; "
        "BENCHMARKS.md names the revision).",
    ),
    sites: str | None = typer.Option(
        None, "--sites", metavar="N,N,…", help="b10: network sizes to run (site counts, comma separated)."
    ),
    rflscm_minutes: float | None = typer.Option(
        None, "--rflscm-minutes", help="b10: also train RF-LSCM with this --minutes budget and evaluate it (min)."
    ),
    device: Device = DeviceOption,
    seed: int = SeedOption,
) -> None:
    """Run a benchmark (speed, memory or accuracy) and record its results as JSON."""
    size = size_choice.value
    load_all()
    console = Console()
    if name == "list":
        for key, (summary, _) in BENCHMARKS.items():
            console.print(f"[bold]{key}[/bold]  {summary}")
        return
    if name not in BENCHMARKS:
        raise ConfigError(f"unknown benchmark {name!r}; choose one of: {', '.join(BENCHMARKS)} (or `list`).")
    if config is not None and name not in ("b9", "b10"):
        raise ConfigError("--config applies to b9 and b10 only.")
    if baseline is not None and name not in ("b9", "render"):
        raise ConfigError("--baseline applies to b9 and render only.")
    if (sites is not None or rflscm_minutes is not None) and name != "b10":
        raise ConfigError("--sites and --rflscm-minutes apply to b10 only.")
    site_counts: tuple[int, ...] = ()
    if sites is not None:
        try:
            site_counts = tuple(int(v) for v in sites.split(",") if v.strip())
        except ValueError:
            raise ConfigError(
                f"--sites must be site counts separated by commas, e.g. 7,19,37 (got {sites!r})."
            ) from None
    if size not in ("quick", "full"):
        raise ConfigError(f"--size must be quick or full (got {size!r}).")
    seed_everything(seed)
    dev = resolve_device(device)
    out.mkdir(parents=True, exist_ok=True)
    ctx = BenchContext(
        size=size,
        seeds=seeds,
        out_dir=out,
        device=str(dev),
        scenario=str(scenario) if scenario else None,
        config=config,
        baseline=baseline,
        sites=site_counts,
        minutes=rflscm_minutes,
    )
    summary, fn = BENCHMARKS[name]
    result = {
        "bench": name,
        "summary": summary,
        "size": size,
        "device": str(dev),
        "machine": _machine(),
        "results": fn(ctx),
    }
    (out / f"{name}.json").write_text(json.dumps(result, indent=2, default=float))
    table = Table(title=f"rflscm bench {name} ({size}, {dev})")
    table.add_column("metric")
    table.add_column("value", justify="right")
    rows: list[tuple[str, str]] = []
    _flatten("", result["results"], rows)
    for key, value in rows:
        table.add_row(key, value)
    console.print(table)
    console.print(f"wrote {out / f'{name}.json'}")
