"""B9 — time to target (issue 15, item 1): RF-LSCM's round-2 MAE against seconds of training, for
*today's model* (an older commit's code, exported into a folder given as ``--baseline PATH``; the
reference runs used ``c7460d6``, and its preset) and *the new one* (the current code's preset, or ``--config``),
side by side in one run, on the same machine and thread count.

Each model trains in its own subprocess (``python b09_worker.py …``, :mod:`rflscm.bench.b09_worker`),
one after the other, never at once: the baseline with ``PYTHONPATH`` at ``PATH/src`` (made once with
``git archive c7460d6 src | tar -x -C PATH``; B9 itself runs no git, so it works from an installed
wheel), the new one at the running package's ``src``; both with the parent's torch thread count
(``rflscm --threads N``) and seed.  Training time counts from the start of the fit (data preparation included); at geometric marks of training time the
worker evaluates the round-2 MAE (adjust protocol) on every cell and on the changed cells, and the
evaluation's wall and CPU time are taken off the clocks (``train_s``, ``cpu_s`` =
``time.process_time``).  WNOMP's level is WNOMP fitted in the current code with the settings chosen
on held-aside round-1 beams (as ``rflscm demo`` does): its ``mae_db.{ssb,csi}.changed``; the new model's
fallback (the pairs a budget's pass does not reach) gets those settings, as in the demo (:func:`with_fallback`).

Reported per regime and beam type: ``old_time_to_wnomp_s`` and ``new_time_to_wnomp_s`` (the first mark
at which the model's changed-cell MAE is at or below WNOMP's; a mark, so resolved to the marks' spacing),
``ratio_old_new`` = old / new; and always ``old_best_mae_db``, ``old_time_to_best_s`` (first mark at
the old model's lowest changed-cell MAE), ``new_time_to_old_best_s`` and ``ratio_to_old_best``, the
comparison the issue asks for where the old model never reaches WNOMP (``basis`` says which one
applies).  One plot per regime: MAE vs training seconds (log x), a panel per beam type, changed cells
solid and all cells dotted, WNOMP's changed-cell level as a horizontal line.

Regimes: the shipped scenario (``field``: sionna munich, field measurements) and its ideal
re-measure (``ideal``: ``rflscm simulate --from-trace … --measurements ideal``, made once into
``<out>/_ideal_scenario`` and reused); ``--scenario DIR`` runs that one scenario instead.  The
baseline code refuses the field regime's ``reporting:`` key, so the baseline reads a copy of the
scenario whose ``scenario.yaml`` lacks it (the other files linked): that is exactly today's model,
whose missing-beam penalty assumes the threshold rule.  The trainers' own periodic validation (the presets'
``val_every``) is part of each model's training and counts.

Sizes: ``quick`` = the whole scenario, both models at their ``quick`` preset (``AngleGrid()``),
the baseline on its step schedule, the new model trained to the demo's budget of 3 minutes
(``rflscm train --minutes 3``: its schedule follows the budget, whose clock also leaves the
evaluations out), marks 5, 7.07, 10, 14.1, 20, … s (×√2: a time to target is resolved to within
41 %; at ×2 a crossing just after a mark counted at the next, up to twice late), each model capped at
1800 s of training, 2 CPU cores (the
baseline's quick schedule takes about 10 min there); ``full`` = the same with the ``full`` presets, no cap
(for a GPU); ``tiny`` (tests only) = a tiny scenario, the tiny overrides, marks of a fraction of a
second.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

from rflscm.bench import BenchContext, register_bench
from rflscm.bench.harness import merge, tiny_size
from rflscm.bench.report import new_figure, save_figure, seeds_of
from rflscm.config import load_yaml
from rflscm.data import BEAM_TYPES
from rflscm.errors import ConfigError
from rflscm.runtime import MALLOC_ENV

DEFAULT_BASELINE = "c7460d6"
"""The commit whose code the reference runs took as the old model (named in the error without ``--baseline``)."""
WORKER = Path(__file__).with_name("b09_worker.py")
MARK_FACTOR = 2**0.5
"""Spacing of the evaluation marks (quick, full): a time to target is known to within this factor."""


def _marks(first: float, last: float, factor: float = 2.0) -> list[float]:
    """``first``, ``first·factor``, ``first·factor²``, … up to ``last`` (rounded to 0.1 ms)."""
    out = [first]
    while out[-1] * factor <= last * (1 + 1e-9):
        out.append(round(first * factor ** len(out), 4))
    return out


def _tiny_overrides() -> dict[str, Any]:
    over = tiny_size().overrides["rflscm"]
    return {
        **over,
        "train": {**over["train"], "steps": 30, "val_every": 10**6},
        "hitam": {**over["hitam"], "warmup_steps": 10, "ramp_steps": 5},
    }


SETTINGS: dict[str, dict[str, Any]] = {  # per size: presets of the old and new model, overrides on both, the
    # angle grid (None: AngleGrid()), evaluation marks [s of training], cap per model [s] (None: whole schedule)
    "tiny": {
        "old_config": "quick",
        "new_config": "quick",
        "overrides": _tiny_overrides(),
        "angle_grid": tiny_size().angle_grid,
        "marks_s": _marks(0.25, 64.0),
        "max_train_s": 60.0,
        "new_minutes": None,
    },
    "quick": {
        "old_config": "quick",
        "new_config": "quick",
        "overrides": {},
        "angle_grid": None,
        "marks_s": _marks(5.0, 1800.0, MARK_FACTOR),
        "max_train_s": 1800.0,
        "new_minutes": 3.0,
    },
    "full": {
        "old_config": "full",
        "new_config": "full",
        "overrides": {},
        "angle_grid": None,
        "marks_s": _marks(5.0, 86400.0, MARK_FACTOR),
        "max_train_s": None,
        "new_minutes": None,
    },
}


@register_bench(
    "b9", "time to target: old (--baseline PATH) vs new RF-LSCM, round-2 MAE vs training seconds against WNOMP"
)
def run(ctx: BenchContext) -> dict[str, Any]:
    return run_b9(ctx, ctx.size)


def run_b9(ctx: BenchContext, size: str) -> dict[str, Any]:
    settings = dict(SETTINGS[size])
    out_dir = Path(ctx.out_dir).resolve()
    old_src = baseline_src(ctx.baseline)
    new_config = ctx.config or settings["new_config"]
    if Path(new_config).suffix in (".yaml", ".yml"):
        new_config = str(Path(new_config).resolve())
    new_src = Path(__file__).resolve().parents[2]
    threads = torch.get_num_threads()
    seed = seeds_of(ctx)[0]
    result: dict[str, Any] = {
        "notes": __doc__.split("\n\n")[-1].strip(),
        "settings": {
            **settings,
            "new_config": new_config,
            "baseline": str(old_src),
            "threads": threads,
            "seed": seed,
            "device": ctx.device,
        },
        "regimes": {},
        "plots": [],
    }
    for regime, path in regimes(ctx).items():
        wnomp = wnomp_level(path, settings["angle_grid"], seed, ctx.device)
        common = dict(
            marks=settings["marks_s"],
            max_s=settings["max_train_s"],
            overrides=settings["overrides"],
            grid=settings["angle_grid"],
            threads=threads,
            seed=seed,
            device=ctx.device,
        )
        old_scen = without_reporting(path, out_dir / "_baseline_scenarios" / regime)
        work = out_dir / "b9_runs"
        old = run_worker(old_src, old_scen, settings["old_config"], work / f"{regime}_old.json", **common)
        new = run_worker(
            new_src,
            path,
            new_config,
            work / f"{regime}_new.json",
            minutes=settings["new_minutes"],
            **{**common, "overrides": with_fallback(settings["overrides"], wnomp["config"])},
        )
        entry = {
            "scenario": str(path),
            "wnomp": wnomp,
            "old": old,
            "new": new,
            "comparison": {
                bt: compare(old["rows"], new["rows"], bt, wnomp["mae_db"][bt]["changed"]) for bt in BEAM_TYPES
            },
        }
        result["regimes"][regime] = entry
        labels = {"old": f"old {old_src.parent.name}", "new": f"new {new_config}"}
        result["plots"].append(plot(ctx, regime, entry, labels))
    return result


def with_fallback(overrides: dict[str, Any], wnomp_config: dict[str, Any]) -> dict[str, Any]:
    """The new model's overrides: WNOMP's selected settings for its fallback (the pairs a budget's pass does not
    reach get WNOMP's APS of their reports with the very settings of the level it is compared with, as
    ``rflscm demo`` gives them), under ``overrides`` (which win).  The baseline's code has no such key."""
    return merge({"corrections": {"wnomp_fallback": dict(wnomp_config)}}, overrides)


# --- the pure summary ----------------------------------------------------------------------------------
def time_to(
    rows: Sequence[dict[str, Any]], beam_type: str, level: float | None, cells: str = "changed"
) -> float | None:
    """The fewest training seconds of a row whose MAE [dB] (``cells`` of ``beam_type``) is at or below ``level``
    (rows are in step order; a row's time includes its own ``finish_training``, so times need not rise)."""
    if level is None or not np.isfinite(level):
        return None
    times = [float(row["train_s"]) for row in rows if (mae := _mae(row, beam_type, cells)) is not None and mae <= level]
    return min(times) if times else None


def best(rows: Sequence[dict[str, Any]], beam_type: str, cells: str = "changed") -> tuple[float | None, float | None]:
    """``(lowest MAE, training seconds of the first row reaching it)``; ``(None, None)`` without a finite MAE."""
    values = [(m, float(r["train_s"])) for r in rows if (m := _mae(r, beam_type, cells)) is not None]
    if not values:
        return None, None
    low = min(m for m, _ in values)
    return low, min(t for m, t in values if m == low)


def compare(
    old: Sequence[dict[str, Any]], new: Sequence[dict[str, Any]], beam_type: str, wnomp_mae: float | None
) -> dict[str, Any]:
    """Time to WNOMP's changed-cell MAE of both models and their ratio old / new; the old model's best and
    the new model's time to it (the comparison where the old model never reaches WNOMP)."""
    old_t, new_t = time_to(old, beam_type, wnomp_mae), time_to(new, beam_type, wnomp_mae)
    old_best, old_best_t = best(old, beam_type)
    new_to_best = time_to(new, beam_type, old_best)
    return {
        "wnomp_mae_db": wnomp_mae,
        "old_time_to_wnomp_s": old_t,
        "new_time_to_wnomp_s": new_t,
        "ratio_old_new": _ratio(old_t, new_t),
        "old_best_mae_db": old_best,
        "new_best_mae_db": best(new, beam_type)[0],
        "old_time_to_best_s": old_best_t,
        "new_time_to_old_best_s": new_to_best,
        "ratio_to_old_best": _ratio(old_best_t, new_to_best),
        "basis": "wnomp" if old_t is not None else "old_best",
    }


def _mae(row: dict[str, Any], beam_type: str, cells: str) -> float | None:
    value = ((row.get("mae_db") or {}).get(beam_type) or {}).get(cells)
    return float(value) if value is not None and np.isfinite(value) else None


def _ratio(slow: float | None, fast: float | None) -> float | None:
    return None if slow is None or fast is None or fast <= 0 else float(slow / fast)


# --- scenarios, the baseline's code, WNOMP, the worker -------------------------------------------------
def regimes(ctx: BenchContext) -> dict[str, Path]:
    """``{"given": --scenario}``, else the shipped scenario (``field``) and its ideal re-measure (``ideal``)."""
    if ctx.scenario:
        return {"given": Path(ctx.scenario).resolve()}
    from rflscm.sim import default_scenario_path

    shipped = default_scenario_path()
    return {"field": shipped, "ideal": ideal_scenario(shipped, Path(ctx.out_dir) / "_ideal_scenario")}


def ideal_scenario(source: Path, out: Path) -> Path:
    """``rflscm simulate --from-trace SOURCE --measurements ideal --out OUT``, once (an existing one is reused)."""
    if (out / "scenario.yaml").is_file():
        return out.resolve()
    from rflscm.config import from_dict, to_dict
    from rflscm.sim import SimulationConfig
    from rflscm.sim.remeasure import remeasure, trace_config

    cfg = from_dict(SimulationConfig, {**to_dict(trace_config(source)), "measurements": "ideal"})
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=f".{out.name}.", dir=out.parent) as tmp:
        remeasure(source, cfg, Path(tmp) / "scenario")
        shutil.rmtree(out, ignore_errors=True)
        shutil.move(str(Path(tmp) / "scenario"), str(out))
    return out.resolve()


def without_reporting(source: Path, out: Path) -> Path:
    """A copy of scenario ``source`` for the baseline code: its files linked, ``scenario.yaml`` without
    ``reporting`` (remade on every run)."""
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    for item in Path(source).iterdir():  # hard links: they stay inside the folder (reads may not leave it)
        if item.name == "scenario.yaml":
            continue
        if item.is_dir():
            shutil.copytree(item.resolve(), out / item.name, copy_function=_link_or_copy)
        else:
            _link_or_copy(str(item.resolve()), str(out / item.name))
    meta = load_yaml(Path(source) / "scenario.yaml")  # strict keys, bounded aliases, regular files only
    meta.pop("reporting", None)
    (out / "scenario.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    return out.resolve()


def _link_or_copy(source: str, target: str) -> None:
    try:
        os.link(source, target)
    except OSError:  # another file system
        shutil.copy2(source, target)


def baseline_src(path: str | Path | None, bench: str = "b9", commit: str = DEFAULT_BASELINE) -> Path:
    """The baseline's ``src``: ``path`` itself or ``path/src``, whichever holds ``rflscm/__init__.py``;
    a one-line :class:`ConfigError` when ``path`` is missing or holds no exported ``src`` (naming ``bench`` and
    the ``commit`` to export)."""
    how = f"git archive {commit} src | tar -x -C PATH"
    if path is None:
        raise ConfigError(f"{bench} needs --baseline PATH, a folder holding the old model's exported src (`{how}`).")
    folder = Path(path).expanduser()
    for src in (folder / "src", folder):
        if (src / "rflscm" / "__init__.py").is_file():
            return src.resolve()
    raise ConfigError(f"{bench}: --baseline {folder} holds no src/rflscm/__init__.py (make it with `{how}`).")


def wnomp_level(path: Path, angle_grid: tuple | None, seed: int, device: str) -> dict[str, Any]:
    """WNOMP (current code) with the settings chosen on held-aside round-1 beams: its round-2 MAE."""
    from rflscm.config import to_dict
    from rflscm.data import load_scenario
    from rflscm.eval import run_evaluation
    from rflscm.eval.protocols import AdjustProtocol, fit_with_protocol
    from rflscm.geometry import AngleGrid
    from rflscm.models import MODEL_REGISTRY
    from rflscm.models.wnomp_select import select_wnomp

    scen = load_scenario(path)
    grid = AngleGrid(*angle_grid) if angle_grid else AngleGrid()
    cfg, _ = select_wnomp(scen, grid, seed=seed, device=device)
    torch.manual_seed(seed)
    model = MODEL_REGISTRY["wnomp"].build(to_dict(cfg), grid, device)
    t0 = time.perf_counter()
    fit_with_protocol(model, scen, AdjustProtocol(), progress=False)
    fit_s = time.perf_counter() - t0
    metrics = run_evaluation(model, scen, AdjustProtocol(), oracle=None, max_aps_pairs=0).metrics
    mae = {bt: {k: _finite(metrics["mae_db"][bt][k]) for k in ("all", "changed")} for bt in BEAM_TYPES}
    return {"config": to_dict(cfg), "mae_db": mae, "fit_s": fit_s}


def _finite(value: Any) -> float | None:
    return float(value) if value is not None and np.isfinite(value) else None


def run_worker(
    src: Path,
    scenario: Path,
    config: str,
    out: Path,
    *,
    marks: list[float],
    max_s: float | None,
    overrides: dict[str, Any],
    grid: tuple | None,
    threads: int,
    seed: int,
    device: str,
    minutes: float | None = None,
) -> dict[str, Any]:
    """Run :mod:`~rflscm.bench.b09_worker` with ``PYTHONPATH=src``; its JSON (rows of the MAE over training time).
    ``minutes``: train to that budget (``rflscm train --minutes``; today's code only) instead of the step schedule."""
    out.parent.mkdir(parents=True, exist_ok=True)
    cmd = [
        sys.executable,
        str(WORKER),
        "--scenario",
        str(scenario),
        "--config",
        config,
        "--out",
        str(out),
        "--overrides",
        json.dumps(overrides),
        "--marks",
        ",".join(f"{m:g}" for m in marks),
        "--threads",
        str(threads),
        "--seed",
        str(seed),
        "--device",
        device,
    ]
    if grid:
        cmd += ["--angle-grid", ",".join(f"{v:g}" for v in grid)]
    if max_s is not None:
        cmd += ["--max-seconds", f"{max_s:g}"]
    if minutes is not None:
        cmd += ["--minutes", f"{minutes:g}"]
    path = os.pathsep.join([str(src), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))])
    # both models run with the allocator settings `rflscm` itself applies (rflscm.runtime): the same process setup
    env = {
        **MALLOC_ENV,
        **os.environ,
        "PYTHONPATH": path,
        "OMP_NUM_THREADS": str(threads),
        "RFLSCM_THREADS": str(threads),
    }
    log = out.with_suffix(".log")
    with log.open("w") as fh:
        done = subprocess.run(cmd, env=env, stdout=fh, stderr=subprocess.STDOUT, cwd=out.parent)
    if done.returncode != 0:
        tail = log.read_text().strip().splitlines()[-1:] or ["no output"]
        raise ConfigError(f"b9: the worker ({src}) failed with exit status {done.returncode}: {tail[0]} (log: {log})")
    result: dict[str, Any] = json.loads(out.read_text())
    if not Path(result["rflscm_file"]).is_relative_to(src):
        raise ConfigError(f"b9: the worker imported {result['rflscm_file']}, not the code under {src}.")
    result["log"] = str(log)
    return result


# --- plot ----------------------------------------------------------------------------------------------
def plot(ctx: BenchContext, regime: str, entry: dict[str, Any], labels: dict[str, str]) -> str:
    from matplotlib.ticker import NullFormatter

    fig, axes = new_figure(ncols=2)
    for ax, bt in zip(axes, BEAM_TYPES, strict=True):
        for who, color in (("old", "tab:grey"), ("new", "tab:blue")):
            rows = sorted(entry[who]["rows"], key=lambda r: r["train_s"])  # a row carries its own finish time
            t = [max(r["train_s"], 1e-3) for r in rows]
            for cells, style in (("changed", "-"), ("all", ":")):
                y = [_mae(r, bt, cells) for r in rows]
                ax.plot(
                    t,
                    [np.nan if v is None else v for v in y],
                    style,
                    marker="o" if cells == "changed" else None,
                    color=color,
                    label=f"{labels[who]} ({cells} cells)",
                )
        level = entry["wnomp"]["mae_db"][bt]["changed"]
        if level is not None:
            ax.axhline(level, color="tab:red", linewidth=0.9, linestyle="--", label=f"WNOMP changed {level:.2f} dB")
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel("training time [s]")
        ax.set_ylabel("round-2 MAE [dB]")
        ax.set_title(f"B9 {regime}: {'SSB' if bt == 'ssb' else 'CSI-RS'}")
        ax.legend(fontsize=7)
    return save_figure(fig, ctx, f"b9_{regime}")
