"""``rflscm import``: raw drive-test / MR samples and a planning tool's cell list → a checked scenario folder."""

from __future__ import annotations

import enum
import shutil
import tempfile
from pathlib import Path
from typing import Any

import typer
from rich.console import Console
from rich.table import Table

from rflscm.cli import app
from rflscm.cli.common import check_numbers, refuse_inputs_inside
from rflscm.errors import ConfigError, DataError


class BeamType(enum.StrEnum):
    ssb = "ssb"
    csi = "csi"


class TableFormat(enum.StrEnum):
    parquet = "parquet"
    csv = "csv"


def parse_pairs(items: list[str], option: str) -> dict[str, str]:
    """``["a=b", …]`` → ``{a: b}``; an item without ``=`` is a :class:`ConfigError` naming the option."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key.strip() or not value.strip():
            raise ConfigError(f"{option} {item!r}: write NAME=VALUE, e.g. {option} lat=Latitude.")
        out[key.strip()] = value.strip()
    return out


def parse_reporting(items: list[str]) -> dict[str, Any]:
    """``csi=top_n:4``, ``ssb=threshold``, ``ssb=sinr:-6:-120.2`` → scenario.yaml ``reporting:``."""
    out: dict[str, Any] = {}
    for beam_type, text in parse_pairs(items, "--reporting").items():
        rule, *args = text.split(":")
        try:
            if rule == "top_n" and len(args) == 1:
                out[beam_type] = {"rule": rule, "top_n": int(args[0])}
            elif rule == "sinr" and len(args) == 2:
                out[beam_type] = {"rule": rule, "detection_db": float(args[0]), "noise_dbm": float(args[1])}
            elif rule == "threshold" and not args:
                out[beam_type] = {"rule": rule}
            else:
                raise ValueError
        except ValueError:
            raise ConfigError(
                f"--reporting {beam_type}={text}: write TYPE=threshold, TYPE=top_n:N or TYPE=sinr:DETECTION_DB:NOISE_DBM."
            ) from None
    return out


def _column_file(path: Path | None) -> dict[str, str]:
    """``--columns FILE``: a YAML mapping rflscm name → your column name."""
    if path is None:
        return {}
    from rflscm.config import load_yaml
    from rflscm.data.ingest.spec import check_columns

    data = {str(k): v for k, v in load_yaml(path).items()}
    data = data.get("columns", data) if isinstance(data.get("columns"), dict) else data
    check_columns(data, str(path))
    return data


def _column_flags(base: dict[str, Any], flags: dict[str, str]) -> dict[str, Any]:
    """``--col`` pairs over the ``--columns`` file; ``--col samples.cell_id=Serving`` maps one table's column."""
    out = {k: dict(v) if isinstance(v, dict) else v for k, v in base.items()}
    for key, value in flags.items():
        table, dot, name = key.partition(".")
        if dot:
            section = out.get(table)
            out[table] = {**(section if isinstance(section, dict) else {}), name: value}
        else:
            out[key] = value
    return out


def parse_origin(text: str) -> dict[str, float]:
    try:
        lat, lon = (float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"--origin {text!r}: write LAT,LON in degrees, e.g. 48.14,11.57.") from None
    return {"lat": lat, "lon": lon}


@app.command("import")
def import_(
    spec: Path | None = typer.Argument(None, help="Import spec YAML (see docs/your-own-data.md); flags override it."),
    out: Path = typer.Option(..., "--out", help="Scenario folder to write (new or empty; see --force)."),
    samples: list[Path] = typer.Option([], "--samples", help="Sample file, CSV or Parquet (repeatable)."),
    cells: list[Path] = typer.Option(
        [], "--cells", help="Cell list (one file; or one per round, in round order: repeat the option)."
    ),
    codebooks: Path | None = typer.Option(None, "--codebooks", help="YAML file with the `codebooks:` mapping."),
    col: list[str] = typer.Option(
        [],
        "--col",
        help="Column name mapping RFLSCM_NAME=YOUR_NAME (repeatable); samples.NAME=… or cells.NAME=… for one table.",
    ),
    columns: Path | None = typer.Option(
        None, "--columns", help="YAML file mapping rflscm column names to yours, e.g. `lat: Latitude` (--col wins)."
    ),
    origin: str | None = typer.Option(
        None, "--origin", help="Origin LAT,LON in degrees (default: centroid of the cells)."
    ),
    grid_size: float | None = typer.Option(None, "--grid-size", help="Grid side (m; default 10)."),
    min_samples: int | None = typer.Option(
        None, "--min-samples", help="Samples a bin needs to be kept (samples; default 3)."
    ),
    outlier_k: float | None = typer.Option(
        None,
        "--outlier-k",
        help="Drop samples more than k·1.4826·MAD from their bin's median in dB (k, count of scaled MADs; default 3; 0: off).",
    ),
    max_distance: float | None = typer.Option(
        None, "--max-distance", help="Farthest (PCI, carrier) match (m; default 10000)."
    ),
    threshold: float | None = typer.Option(
        None,
        "--threshold",
        help="The scenario's rsrp_threshold_dbm (dBm); bins averaging below it are dropped (default: −120 or the weakest bin).",
    ),
    beam_type: BeamType | None = typer.Option(
        None, "--beam-type", help="Beam type of every sample (no beam_type column)."
    ),
    reporting: list[str] = typer.Option(
        [], "--reporting", help="Reporting rule TYPE=threshold | TYPE=top_n:N | ssb=sinr:DETECTION_DB:NOISE_DBM."
    ),
    name: str | None = typer.Option(None, "--name", help="Scenario name."),
    point_cloud: Path | None = typer.Option(
        None,
        "--point-cloud",
        help="Building point cloud to copy in (.ply/.las/.laz/.npy), in the import's local frame: x east, y north "
        "(m) from the origin, z (m) above the origin's height.",
    ),
    terrain: Path | None = typer.Option(
        None,
        "--terrain",
        help="DEM GeoTIFF or XYZ table (x, y, z in m, local frame): cell and UE heights are above it (copied in).",
    ),
    table_format: TableFormat = typer.Option(TableFormat.parquet, "--format", help="Table format of the scenario."),
    force: bool = typer.Option(False, "--force", help="Replace --out if it is an existing scenario folder."),
) -> None:
    """Bin raw samples into grids, resolve cells, and write a scenario that `rflscm check` accepts."""
    from rflscm.cli.simulate import _prepare_out
    from rflscm.data import load_scenario
    from rflscm.data.ingest import import_raw, load_spec
    from rflscm.data.ingest.spec import check_columns
    from rflscm.data.safe_io import guard_outputs

    check_numbers(
        grid_size=(grid_size, 1e-3, 1e5),
        min_samples=(min_samples, 1, 2**31 - 1),
        outlier_k=(outlier_k, 0.0, 1e6),
        max_distance=(max_distance, 0.0, 1e8),
        threshold=(threshold, -300.0, 100.0),
    )
    inputs: list[Path | None] = [spec, *samples, *cells, codebooks, columns, point_cloud, terrain]
    refuse_inputs_inside(out, inputs)
    guard_outputs({"--out": out}, inputs, force=True, folders=("--out",))
    overrides: dict[str, Any] = {
        "samples": [str(p) for p in samples] or None,
        "cells": [str(p) for p in cells] or None,
        "codebooks": None if codebooks is None else str(codebooks),
        "columns": _column_flags(_column_file(columns), parse_pairs(col, "--col")),
        "origin": None if origin is None else parse_origin(origin),
        "grid_size_m": grid_size,
        "min_samples": min_samples,
        "outlier_k": outlier_k,
        "max_distance_m": max_distance,
        "rsrp_threshold_dbm": threshold,
        "beam_type": None if beam_type is None else beam_type.value,
        "reporting": parse_reporting(reporting) or None,
        "name": name,
        "point_cloud": None if point_cloud is None else str(point_cloud),
        "terrain": None if terrain is None else str(terrain),
    }
    check_columns(overrides["columns"], "--col/--columns")
    settings = load_spec(spec, overrides)
    _prepare_out(out, force)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{out.name}.", dir=out.parent) as tmp:
        result = import_raw(settings, Path(tmp) / "scenario", table_format.value)
        try:  # what `rflscm check` does: the import stands only if it passes
            load_scenario(Path(tmp) / "scenario")
        except DataError as exc:
            raise DataError(
                f"import: the scenario it wrote fails `rflscm check` (so {out} was not written): {exc}"
            ) from None
        if out.exists():
            shutil.rmtree(out) if any(out.iterdir()) else out.rmdir()
        shutil.move(str(Path(tmp) / "scenario"), str(out))
    _print(result, out, Console())


def _print(result: Any, out: Path, console: Console) -> None:
    table = Table(title="samples kept and dropped", title_justify="left")
    for column in ("", "samples", "bins"):
        table.add_column(column, justify="left" if not column else "right")
    table.add_row("read", f"{result.samples_read:,}", "")
    for reason, n in result.dropped.samples.items():
        bins = result.dropped.bins.get(reason, 0)
        table.add_row(f"dropped: {reason}", f"{n:,}", f"{bins:,}" if bins else "")
    table.add_row("[bold]kept[/bold]", f"{result.samples_kept:,}", f"{result.bins:,}")
    console.print(table)
    where = "none (x/y in metres)" if result.origin is None else f"{result.origin.lat:.6f}, {result.origin.lon:.6f}"
    chosen = " (default: −120 dBm or the weakest kept bin, rounded down)" if result.threshold_chosen else ""
    console.print(
        f"origin {where}; {result.cells} cells, {result.grids} grids, rounds {result.rounds}; "
        f"rsrp_threshold_dbm {result.threshold_dbm:g}{chosen}"
    )
    if result.point_cloud_points:
        console.print(f"point cloud: {result.point_cloud_points:,} points, copied in (frame checked against the grids)")
    else:
        console.print(
            "no point cloud: the default RF-LSCM needs one for its prior; re-import with --point-cloud FILE, "
            "or train with `--set prior.enabled=false`."
        )
    console.print(f"[green]wrote[/green] {out} (checked). Next: `rflscm check {out}`, `rflscm train {out}`.")
