"""``rflscm simulate``: make a scenario with ground truth from a ray tracer."""

from __future__ import annotations

import dataclasses
import os
import shutil
import tempfile
from enum import StrEnum
from pathlib import Path
from typing import Any

import typer
from rich.console import Console

from rflscm.cli import app
from rflscm.cli.common import Device, DeviceOption, resolve_device, seed_everything
from rflscm.config import load_config
from rflscm.data import SCENARIO_FILE
from rflscm.errors import ConfigError
from rflscm.parallel.engine import Engine, RayAddressOption, WorkersOption


def parse_carriers(text: str) -> tuple[float, ...]:
    """``"3.5e9,2.1e9"`` → carriers [Hz]; values that look like MHz or GHz are a clear error."""
    values = []
    for item in (t.strip() for t in text.split(",")):
        try:
            value = float(item)
        except ValueError:
            raise ConfigError(f"--carriers: {item!r} is not a number; give carriers in Hz, e.g. 3.5e9,2.1e9.") from None
        if not 0 < value < 1e12:  # NaN fails too
            raise ConfigError(f"--carriers: {item} is not a carrier frequency; give finite carriers in Hz below 1e12.")
        if value < 1e8:
            unit, scale = ("GHz", 1e9) if value < 1e3 else ("MHz", 1e6)
            raise ConfigError(
                f"--carriers: {item} looks like {unit}; give carriers in Hz, "
                f"e.g. {value * scale:.4g} for {item} {unit}."
            )
        values.append(value)
    if not values:
        raise ConfigError("--carriers needs at least one carrier in Hz, e.g. 3.5e9.")
    return tuple(values)


def _check_backend(backend: str, scene: str | None) -> None:
    from rflscm.sim import BACKENDS, PROCEDURAL_SCENES

    if backend not in BACKENDS:
        raise ConfigError(f"--backend {backend!r} is unknown; valid backends: {', '.join(BACKENDS)}.")
    if backend == "procedural" and scene is not None and scene not in PROCEDURAL_SCENES:
        raise ConfigError(f"--scene {scene!r} is not a procedural scene; valid: {', '.join(PROCEDURAL_SCENES)}.")
    if backend == "sionna":
        from rflscm.sim.sionna_rt import available_scenes

        names = available_scenes()  # raises ConfigError with the install hint when Sionna is missing
        if scene is not None and scene not in names and not scene.endswith(".xml"):
            raise ConfigError(f"--scene {scene!r} is not a Sionna scene; valid: {', '.join(names)} (or a .xml file).")


def _prepare_out(out: Path, force: bool) -> None:
    if not out.exists():
        return
    if not out.is_dir():
        raise ConfigError(f"--out {out}: exists and is not a folder.")
    if not any(out.iterdir()):
        return
    if not force:
        raise ConfigError(
            f"--out {out}: folder exists and is not empty; pass --force to replace it, or choose another."
        )
    if not (out / SCENARIO_FILE).is_file():
        raise ConfigError(
            f"--out {out}: --force only replaces a scenario folder, and this one has no {SCENARIO_FILE}; "
            "empty it yourself or choose another --out."
        )


class Backend(StrEnum):
    procedural = "procedural"
    sionna = "sionna"


class Regime(StrEnum):
    ideal = "ideal"
    field = "field"


class RawCloud(StrEnum):
    """--raw-cloud choices (rflscm.sim.raw_writer.CLOUD_FORMATS)."""

    same = "same"
    ply = "ply"
    las = "las"
    laz = "laz"
    npy = "npy"
    none = "none"


@app.command()
def simulate(
    out: Path = typer.Option(..., "--out", help="Scenario folder to write (must be new or empty; see --force)."),
    backend_choice: Backend = typer.Option(
        Backend.procedural, "--backend", help="Ray tracer: procedural (built in) or sionna."
    ),
    scene: str | None = typer.Option(
        None,
        "--scene",
        help="Scene: procedural city|small|ground|free_space; sionna munich|etoile|… (default: city / munich).",
    ),
    sites: int | None = typer.Option(None, "--sites", min=1, help="Sites (count; default 7, 3 sectors each)."),
    carriers: str | None = typer.Option(
        None,
        "--carriers",
        help="Carrier frequencies (Hz), comma separated; the first is the primary (default 3.5e9,2.1e9).",
    ),
    grids: int | None = typer.Option(None, "--grids", min=1, help="Most grids of 10 m × 10 m (count; default 800)."),
    config: Path | None = typer.Option(None, "--config", help="SimulationConfig YAML; options given here override it."),
    force: bool = typer.Option(False, "--force", help="Replace --out if it is an existing scenario folder."),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar while tracing."),
    device: Device = DeviceOption,
    seed: int | None = typer.Option(
        None, "--seed", help="Random seed (integer; default: the config's, else 0); the same seed, the same scenario."
    ),
    regime: Regime | None = typer.Option(
        None,
        "--measurements",
        help="Measurement regime: ideal (noise on the "
        "expectation, every beam above r_th) or field (as a network reports "
        "them; effects under `field_model:` in --config). Default: the config's, "
        "else ideal.",
    ),
    from_trace: Path | None = typer.Option(
        None,
        "--from-trace",
        help="Re-measure the paths of this simulated scenario instead of tracing (only measurement keys may change).",
    ),
    raw_out: Path | None = typer.Option(
        None, "--raw-out", help="Also write raw samples.csv, cells.csv and import.yaml here (for `rflscm import`)."
    ),
    raw_samples: int = typer.Option(
        5, "--raw-samples", min=1, help="Raw samples per reported beam and grid (samples)."
    ),
    raw_fading: float = typer.Option(2.0, "--raw-fading", min=0.0, help="Per-sample log-normal fading σ (dB)."),
    raw_grids: int | None = typer.Option(
        None, "--raw-grids", min=1, help="Write raw samples of at most this many grids (grids)."
    ),
    raw_cloud: RawCloud = typer.Option(
        RawCloud.same,
        "--raw-cloud",
        help="Point cloud beside the raw samples: same (the scenario's file), a format (laz is ~4× smaller), or none.",
    ),
    workers: int = WorkersOption,
    ray_address: str | None = RayAddressOption,
) -> None:
    """Trace a scene once per (site, carrier) and write a complete scenario with ground truth (truth/).

    With --workers N (or --ray-address) the traces, and the ideal regime's noiseless RSRP per site and carrier, run
    on Ray workers; the scenario written is the same file for file."""
    backend, measurements = backend_choice.value, None if regime is None else regime.value
    engine = Engine(workers, ray_address)
    from rflscm.cli.common import SEED_MAX, check_numbers, refuse_inputs_inside
    from rflscm.data.safe_io import guard_outputs

    check_numbers(seed=(seed, 0, SEED_MAX), raw_fading=(raw_fading, 0.0, 100.0))
    inputs = [config, from_trace]
    refuse_inputs_inside(out, inputs)
    if raw_out is not None and os.path.realpath(raw_out).startswith(os.path.realpath(out).rstrip(os.sep) + os.sep):
        raise ConfigError(f"--raw-out {raw_out}: is inside --out {out}, which is replaced; choose a folder beside it.")
    guard_outputs({"--out": out, "--raw-out": raw_out}, inputs, force=True, folders=("--out", "--raw-out"))
    from rflscm.parallel.work import mapper as work_mapper
    from rflscm.sim import SimulationConfig, build_scenario, make_backend
    from rflscm.sim.builder import BackendSpec, grow_procedural

    if measurements not in (None, "ideal", "field"):
        raise ConfigError(f"--measurements must be ideal or field (got {measurements!r}).")
    if from_trace is not None:
        layout = [
            flag
            for flag, value in (("--sites", sites), ("--grids", grids), ("--carriers", carriers), ("--scene", scene))
            if value is not None
        ]
        if layout:
            raise ConfigError(
                f"--from-trace re-measures an existing trace, so {', '.join(layout)} cannot change it; drop "
                f"{'them' if len(layout) > 1 else 'it'} or simulate anew without --from-trace."
            )
        _remeasure(from_trace, out, config, measurements, seed, force, engine)
        _write_raw(out, raw_out, raw_samples, raw_fading, raw_grids, seed, raw_cloud.value)
        return
    cfg = load_config(SimulationConfig, config) if config is not None else SimulationConfig()
    overrides: dict[str, Any] = {
        "num_sites": sites,
        "max_grids": grids,
        "seed": seed,
        "measurements": measurements,
        "carriers_hz": parse_carriers(carriers) if carriers is not None else None,
    }
    cfg = dataclasses.replace(cfg, **{k: v for k, v in overrides.items() if v is not None})
    _check_backend(backend, scene)
    scene = scene or ("city" if backend == "procedural" else "munich")
    if backend == "procedural":  # beyond 7 sites the city, its site radius and (without --grids) the grids grow
        cfg = grow_procedural(cfg, scene, scale_grids=grids is None)
    _prepare_out(out, force)
    dev = resolve_device(device)
    seed_everything(cfg.seed)
    spec = BackendSpec(backend, scene, seed=cfg.seed, device=dev.type, options=dict(cfg.backend_options))
    scene_backend = make_backend(backend, scene, seed=cfg.seed, device=dev.type, options=cfg.backend_options)
    out.parent.mkdir(parents=True, exist_ok=True)
    stats: dict[str, float] = {}
    with (
        tempfile.TemporaryDirectory(prefix=f".{out.name}.", dir=out.parent) as tmp,
        work_mapper(engine, "a trace", gpus=dev.type == "cuda" and backend == "sionna") as mapper,
    ):
        build_scenario(
            scene_backend,
            cfg,
            Path(tmp) / "scenario",
            progress=progress,
            scene=scene,
            stats=stats,
            mapper=mapper,
            spec=spec,
        )
        if out.exists():
            shutil.rmtree(out) if any(out.iterdir()) else out.rmdir()
        shutil.move(str(Path(tmp) / "scenario"), str(out))
    console = Console(stderr=True)
    where = ""
    if engine.parallel:
        where = f"; {stats['trace_wall_seconds']:.1f} s wall on {workers} Ray workers"
    console.print(
        f"[green]wrote[/green] {out}: {int(stats['num_cells'])} cells, {int(stats['num_grids'])} grids, "
        f"{stats['paths_per_grid']:.1f} paths per grid and trace, "
        f"{100 * stats['fraction_missing']:.1f} % beams missing; "
        f"tracing {stats['trace_seconds']:.1f} s ({stats['seconds_per_1000_rx_per_carrier']:.2f} s per 1000 "
        f"receivers per carrier{where}). Check it with `rflscm check {out}`."
    )
    _write_raw(out, raw_out, raw_samples, raw_fading, raw_grids, cfg.seed, raw_cloud.value)


def _write_raw(
    scenario: Path,
    raw_out: Path | None,
    samples: int,
    fading_db: float,
    grids: int | None,
    seed: int | None,
    cloud: str = "same",
) -> None:
    """``--raw-out``: the written scenario as raw samples and a cell list (rflscm.sim.raw_writer)."""
    if raw_out is None:
        return
    from rflscm.cli.common import output_folder
    from rflscm.data import load_scenario
    from rflscm.sim.raw_writer import write_raw

    sc = load_scenario(scenario)
    info = write_raw(
        sc,
        output_folder(raw_out, "--raw-out"),
        samples_per_beam=samples,
        fading_db=fading_db,
        max_grids=grids,
        grid_size_m=float(sc.meta.simulation.get("config", {}).get("grid_size_m", 10.0)),
        seed=seed or 0,
        point_cloud=cloud,
    )
    Console(stderr=True).print(
        f"[green]wrote[/green] raw {raw_out}: {info['samples']:,} samples of {info['grids']} grids, "
        f"{info['cells']} cell rows"
        + (f", point cloud of {info['cloud_points']:,} points" if info["cloud_points"] else ", no point cloud")
        + f". Import with `rflscm import {raw_out / 'import.yaml'} --out DIR`."
    )


def _remeasure(
    source: Path,
    out: Path,
    config: Path | None,
    measurements: str | None,
    seed: int | None,
    force: bool,
    engine: Engine,
) -> None:
    """``--from-trace``: the trace's recorded config, overridden by the measurement keys of --config and the flags."""
    from rflscm.config import from_dict, load_yaml, to_dict
    from rflscm.sim import SimulationConfig
    from rflscm.sim.remeasure import remeasure, trace_config

    merged = to_dict(trace_config(source))
    if config is not None:
        merged.update(load_yaml(config))  # strict keys, bounded aliases, regular files only
    for key, value in (("measurements", measurements), ("seed", seed)):
        if value is not None:
            merged[key] = value
    cfg = from_dict(SimulationConfig, merged)
    _prepare_out(out, force)
    out.parent.mkdir(parents=True, exist_ok=True)
    from rflscm.parallel.work import mapper as work_mapper

    if cfg.measurements == "field" and engine.parallel:  # only the ideal regime's RSRP runs per site on workers
        Console(stderr=True).print("--workers: the field regime is measured in this process; no Ray is started.")
        engine = Engine()
    with (
        tempfile.TemporaryDirectory(prefix=f".{out.name}.", dir=out.parent) as tmp,
        work_mapper(engine, "a site's RSRP") as mapper,
    ):
        remeasure(source, cfg, Path(tmp) / "scenario", mapper=mapper)
        if out.exists():
            shutil.rmtree(out) if any(out.iterdir()) else out.rmdir()
        shutil.move(str(Path(tmp) / "scenario"), str(out))
    Console(stderr=True).print(
        f"[green]wrote[/green] {out}: {source} re-measured in the {cfg.measurements} regime. "
        f"Check it with `rflscm check {out}`."
    )
