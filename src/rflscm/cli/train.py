"""``rflscm train``: fit a model on a scenario's round-1 data and write a checkpoint."""

from __future__ import annotations

import time
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.console import Console

from rflscm.cli import app
from rflscm.cli.common import (
    SEED_MAX,
    Device,
    DeviceOption,
    ForceOption,
    Interrupted,
    SeedOption,
    budget_note,
    budget_seconds,
    budget_summary,
    check_numbers,
    command_start,
    resolve_device,
    seed_everything,
)
from rflscm.cli.overrides import PresetOption, SetOption, model_config
from rflscm.errors import ConfigError, RflscmError
from rflscm.parallel.engine import Engine, RayAddressOption, WorkersOption

if TYPE_CHECKING:
    import torch

    from rflscm.data.scenario import Scenario


def protocol_options(
    protocol: str, holdout: float, train_percent: float, other_carriers: bool, split_seed: int
) -> dict[str, object]:
    """The settings of ``--protocol`` from the CLI options that belong to it."""
    if protocol == "unseen":
        return {"fraction": holdout, "seed": split_seed}
    if protocol == "multifreq":
        return {"train_percent": train_percent, "with_other_carriers": other_carriers, "seed": split_seed}
    return {}


def config_inputs(config: str) -> list[Path]:
    """The YAML file ``--config`` names (a preset name is no file)."""
    return [Path(config)] if config.lower().endswith((".yaml", ".yml")) else []


def interrupted_note(out: Path, scenario: Path) -> str:
    """What an interrupted ``train`` left at ``out`` and how to continue it."""
    from rflscm.models.base import read_checkpoint

    try:
        state = read_checkpoint(out)["state"] if out.is_file() else None
    except RflscmError:
        state = None
    if state is None:
        return f"no checkpoint was saved at {out}; run the same `rflscm train` command again."
    step = state.get("step") if isinstance(state, dict) else None
    at = f" (step {step})" if step is not None else ""
    return (
        f"the last checkpoint{at} at {out} is kept and marked interrupted; continue it with "
        f"`rflscm train {scenario} --out {out} --resume` and the same options."
    )


@dataclass(frozen=True)
class TiledRun:
    """The options of a tiled training run (``--tile-sites``)."""

    model: str
    config: str | dict[str, Any]
    tile_sites: int
    device: torch.device
    seed: int
    engine: Engine
    progress: bool


def train_tiled(
    run: TiledRun,
    scen: Scenario,
    proto: Any,
    budget_s: float | None,
    started: float,
    out: Path,
    run_info: dict[str, Any],
    console: Console,
) -> None:
    """Fit a tiled model (:func:`rflscm.train.tiles.fit_tiled`; Ray tasks with more than one worker) and save it."""
    from rflscm.train.tiles import fit_tiled

    runner = None
    if run.engine.parallel:
        from rflscm.parallel.tiles import ray_runner

        runner = ray_runner(run.engine, gpus=run.device.type == "cuda")
    tiled = fit_tiled(
        run.model,
        run.config,
        scen,
        proto,
        run.tile_sites,
        budget_s=budget_s,
        started=started,
        device=run.device,
        seed=run.seed,
        runner=runner,
        report=console.print,
        progress=run.progress,
        run_info=run_info,
    )
    tiled.run_info["fit"]["train_time_s"] = time.perf_counter() - started
    tiled.save(out)
    elapsed = time.perf_counter() - started
    tiles = len(tiled.tiles)
    console.print(f"wrote {out} ({tiles} tiles, {len(tiled.cell_ids)} cells) in {elapsed:.1f} s")
    if budget_s is not None:
        console.print(f"{elapsed:.1f} s in all of a {budget_s / 60:g}-minute budget")


class ModelName(StrEnum):
    rflscm = "rflscm"
    nerf2 = "nerf2"
    wnomp = "wnomp"


class Protocol(StrEnum):
    adjust = "adjust"
    unseen = "unseen"
    multifreq = "multifreq"


@app.command()
def train(
    scenario: Path = typer.Argument(..., help="Scenario folder (or its scenario.yaml)."),
    model_choice: ModelName = typer.Option(ModelName.rflscm, "--model", help="Model: rflscm, nerf2 or wnomp."),
    config: str = typer.Option(
        "quick", "--config", help="Preset (quick, full) or a YAML file of the settings that differ from --preset."
    ),
    preset: str | None = PresetOption,
    sets: list[str] = SetOption,
    out: Path = typer.Option(Path("runs/model.ckpt"), "--out", help="Checkpoint file to write."),
    protocol_choice: Protocol = typer.Option(
        Protocol.adjust, "--protocol", help="Which data to train on: adjust, unseen or multifreq."
    ),
    holdout: float = typer.Option(0.1, "--holdout", help="unseen: share of the grids held out (fraction, 0…1)."),
    train_percent: float = typer.Option(
        10.0, "--train-percent", help="multifreq: share of the low carrier's grids to train on (%)."
    ),
    other_carriers: bool = typer.Option(
        True, "--other-carriers/--no-other-carriers", help="multifreq: also train on the other carriers."
    ),
    split_seed: int = typer.Option(0, "--split-seed", help="Seed of the protocol's grid split (integer)."),
    resume: bool = typer.Option(False, "--resume", help="Continue exactly from --out (iterative models)."),
    minutes: float | None = typer.Option(
        None,
        "--minutes",
        help="Training budget of wall time (min; iterative models): learning-rate decay, HiTAM warm-up and "
        "ramp follow the elapsed fraction of the budget, `train.steps` is the nominal schedule's length.",
    ),
    progress: bool = typer.Option(True, "--progress/--no-progress", help="Show a progress bar."),
    tile_sites: int = typer.Option(
        0,
        "--tile-sites",
        min=0,
        metavar="K",
        help="Split the network into tiles of about K sites, one model each, saved as one tiled model "
        "(count of sites; 0: one model for the whole network).",
    ),
    workers: int = WorkersOption,
    ray_address: str | None = RayAddressOption,
    device: Device = DeviceOption,
    seed: int = SeedOption,
    force: bool = ForceOption,
) -> None:
    """Fit a model on round-1 measurements and save a checkpoint (config, weights, data fingerprint)."""
    model, protocol = model_choice.value, protocol_choice.value
    from rflscm.data import load_scenario
    from rflscm.data.loader import scenario_inputs
    from rflscm.data.safe_io import guard_outputs
    from rflscm.eval.protocols import fit_with_protocol, make_protocol
    from rflscm.geometry import AngleGrid
    from rflscm.models import MODEL_REGISTRY
    from rflscm.models.base import read_checkpoint
    from rflscm.train import Trainable

    check_numbers(
        holdout=(holdout, 0.0, 1.0),
        train_percent=(train_percent, 0.0, 100.0),
        seed=(seed, 0, SEED_MAX),
        split_seed=(split_seed, 0, SEED_MAX),
    )
    guard_outputs({"--out": out}, [*scenario_inputs(scenario), *config_inputs(config)], force=force, resume=resume)
    t0 = command_start()  # a --minutes budget counts from the command's start: imports and loading are part of it
    console = Console(stderr=True)
    if model not in MODEL_REGISTRY:
        valid = ", ".join(sorted(MODEL_REGISTRY))
        raise ConfigError(f"unknown model {model!r}; choose one of: {valid}.")
    budget_s = budget_seconds(minutes)
    if resume and not out.is_file():
        raise ConfigError(f"--resume needs an existing checkpoint at {out}; train without --resume first.")
    seed_everything(seed)
    dev = resolve_device(device)
    engine = Engine(workers, ray_address)
    if tile_sites == 0 and engine.parallel:
        raise ConfigError("--workers and --ray-address train tiles in parallel: give --tile-sites K as well.")
    if tile_sites > 0 and resume:
        raise ConfigError("--resume does not apply to a tiled model (--tile-sites); train it again without --resume.")
    scen = load_scenario(scenario)
    proto = make_protocol(protocol, **protocol_options(protocol, holdout, train_percent, other_carriers, split_seed))
    if tile_sites > 0:
        run_info = {"seed": seed, "config": config}
        if sets or preset is not None:
            run_info["config_overrides"] = {"preset": preset, "set": list(sets)}
        where = f"{workers} Ray workers" if engine.parallel else "in turn"
        console.print(
            f"training [bold]{model}[/bold] ({config}) on {scen.meta.name!r} with protocol {protocol} on {dev}, "
            f"in tiles of about {tile_sites} sites ({where})"
        )
        probe = MODEL_REGISTRY[model].build(model_config(model, config, preset, sets), AngleGrid(), dev)
        if budget_s is not None and not isinstance(probe, Trainable):
            console.print(f"note: --minutes does not apply to {model} (it is not trained step by step); ignored.")
            budget_s = None
        elif budget_s is not None:
            console.print(f"time budget: {minutes:g} min for every tile together (data preparation included)")
        train_tiled(
            TiledRun(model, model_config(model, config, preset, sets), tile_sites, dev, seed, engine, progress),
            scen,
            proto,
            budget_s,
            t0,
            out,
            run_info,
            console,
        )
        return
    fitted = MODEL_REGISTRY[model].build(model_config(model, config, preset, sets), AngleGrid(), dev)
    fitted.run_info["seed"] = seed
    fitted.run_info["config"] = config
    if sets or preset is not None:
        fitted.run_info["config_overrides"] = {"preset": preset, "set": list(sets)}
    console.print(f"training [bold]{model}[/bold] ({config}) on {scen.meta.name!r} with protocol {protocol} on {dev}")
    if budget_s is not None and not isinstance(fitted, Trainable):
        console.print(f"note: --minutes does not apply to {model} (it is not trained step by step); ignored.")
        budget_s = None
    elif budget_s is not None:
        console.print(f"time budget: {minutes:g} min (data preparation included)")
    fitted.run_info["interrupted"] = True  # every checkpoint saved during training says so, until the last one
    try:
        summary = fit_with_protocol(
            fitted, scen, proto, progress=progress, checkpoint_path=out, resume=resume, budget_s=budget_s, started=t0
        )
    except Interrupted as exc:
        raise Interrupted(exc.signum, interrupted_note(out, scenario)) from None
    if not isinstance(fitted, Trainable):  # a step-by-step model's fit wrote its finished checkpoint itself
        fitted.run_info.pop("interrupted")
        fitted.run_info["fit"] = {**{k: float(v) for k, v in summary.items()}, "train_time_s": time.perf_counter() - t0}
        kept = read_checkpoint(out).get("train_state") if out.is_file() else None
        fitted.save(out, train_state=kept)
    elapsed = time.perf_counter() - t0
    console.print(f"wrote {out} in {elapsed:.1f} s")
    if (line := budget_summary(summary)) is not None:
        console.print(line)
    if (note := budget_note(summary)) is not None:
        console.print(note)
