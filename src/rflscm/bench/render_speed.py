"""Inference rendering speed of RF-LSCM (issue 29): ``model.aps`` pairs per second, old code against new.

An RF-LSCM is trained in step mode (deterministic with ``--threads 1``) for a fixed short schedule on the
scenario (the shipped one by default): the ``quick`` (``full``) preset with :data:`SCHEDULE` laid over it, the
HiTAM warm-up and ramp shortened so that the saved model renders through its coarse pass, selection and
refinement pass as a fully trained one does, and with its pair corrections (levels, anchors, posterior), which
``aps`` applies.  The pass after training (``finish_training``: one render of every training pair, then the
corrections' fits) is run once more and timed.

Two patterns of pairs are rendered: ``by_cell``, a few cells with many grids each (what ``predict``, ``map``,
``optimize`` and :class:`~rflscm.eval.cache.ScenarioAPS` ask: per cell, all grids), and ``mixed``, pairs drawn
at random over every cell and grid (scattered evaluation pairs: few grids share a cell's rays).  The timing runs
in a worker process (:mod:`rflscm.bench.render_worker`, run by path) per code version: the current ``src`` and,
with ``--baseline PATH``, an older commit's exported ``src``, in turn (new, old, new, old, …: both see the same
machine load), :data:`ROUNDS` rounds; medians are reported, and the speed-ups as medians of the per-round
ratios.  Throughput is given per wall second and per CPU second of the process (with ``--threads 1``, what
the work costs whatever else runs on the machine).  Checks: the new APS against the old code's (exact
equality and the largest difference relative to the row's peak), and the inference path (no gradients)
against the training path (gradients on, the code the trainer runs) on a few pairs.  The first round's
workers also profile one ``by_cell`` call (cProfile, the functions with the largest cumulative time).
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from rflscm.bench import BenchContext, register_bench
from rflscm.bench.harness import merge, scenario_path
from rflscm.errors import RflscmError

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.models.rflscm import RFLSCM

SCHEDULE: dict[str, Any] = {
    "train": {"steps": 60, "val_every": 60, "val_pairs": 64, "checkpoint_every": 10**6},
    "hitam": {"warmup_steps": 30, "ramp_steps": 15},
}
"""Laid over the preset: a short schedule that ends past HiTAM's warm-up and ramp (the refinement model renders)."""
PATTERNS: dict[str, tuple[tuple[int, int], int]] = {"quick": ((4, 512), 512), "full": ((8, 800), 4096)}
"""Per size: ``by_cell`` (cells, grids per cell) and ``mixed`` (pairs)."""
BASELINE = "210ae3a"
"""The commit before issue 29's rendering work (what BENCHMARKS compares against)."""
ROUNDS = 3
"""Worker runs per code version (alternating with the baseline's)."""
REFERENCE_PAIRS = 24
"""Pairs rendered with and without gradients for the inference-path check."""


@register_bench("render", "RF-LSCM inference rendering: model.aps pairs/s and peak memory, new vs --baseline code")
def run(ctx: BenchContext) -> dict[str, Any]:
    from rflscm.bench.b09_time_to_target import baseline_src

    old_src = baseline_src(ctx.baseline, "render", BASELINE) if ctx.baseline is not None else None
    new_src = Path(__file__).resolve().parents[2]
    out_dir = Path(ctx.out_dir)
    path, source = scenario_path(ctx)
    from rflscm.data import load_scenario

    scenario = load_scenario(path)
    model, train_info = _train(ctx, scenario)
    ckpt = out_dir / "render_model.ckpt"
    model.save(ckpt)
    pairs_file = out_dir / "render_pairs.npz"
    patterns = _patterns(scenario, ctx.size)
    np.savez(pairs_file, **patterns)  # type: ignore[arg-type]
    result: dict[str, Any] = {
        "scenario": {
            "path": str(path),
            "source": source,
            "cells": len(scenario.cell_ids()),
            "grids": len(scenario.grid_ids()),
        },
        "train": train_info,
        "patterns": {
            name: {
                "pairs": int(len(patterns[f"{name}_cells"])),
                "cells": int(len(np.unique(patterns[f"{name}_cells"]))),
            }
            for name in _names(patterns)
        },
        "inference_vs_training_path": _grad_reference(model, patterns),
        "baseline": str(old_src) if old_src is not None else None,
        "notes": __doc__.split("\n\n")[-1].replace("\n", " "),
    }
    versions = {"new": new_src} if old_src is None else {"new": new_src, "old": old_src}
    runs: dict[str, list[dict[str, Any]]] = {v: [] for v in versions}
    aps: dict[str, dict[str, torch.Tensor]] = {}
    threads = torch.get_num_threads()
    with tempfile.TemporaryDirectory(prefix="render-bench-") as tmp:
        for r in range(ROUNDS):
            for label, src in versions.items():
                target = Path(tmp) / f"{label}.pt"
                runs[label].append(_worker(src, ckpt, pairs_file, target, threads, profile=r == 0))
                aps[label] = torch.load(target, weights_only=True)
    result["profile"] = {label: rows[0].pop("profile", None) for label, rows in runs.items()}
    (out_dir / "render_runs.json").write_text(json.dumps(runs, indent=2))
    result["runs"] = str(out_dir / "render_runs.json")
    result["summary"] = {label: _summary(rows, _names(patterns)) for label, rows in runs.items()}
    if "old" in runs:
        result["speedup"] = {
            name: {
                unit: statistics.median(
                    o[name][f"{unit}_s"] / n[name][f"{unit}_s"] for n, o in zip(runs["new"], runs["old"])
                )
                for unit in ("wall", "cpu")
            }
            for name in _names(patterns)
        }
        result["new_vs_old_aps"] = {name: _compare(aps["new"][name], aps["old"][name]) for name in _names(patterns)}
    return result


def _names(patterns: dict[str, np.ndarray]) -> list[str]:
    return sorted({k.rsplit("_", 1)[0] for k in patterns})


def _train(ctx: BenchContext, scenario: Scenario) -> tuple[RFLSCM, dict[str, Any]]:
    """The short-schedule model (step mode) and the times of its training and of its pass after training."""
    from rflscm.config import load_yaml
    from rflscm.models.rflscm import RFLSCM
    from rflscm.models.rflscm.config import preset_path
    from rflscm.train import fit

    cfg = merge(load_yaml(preset_path(ctx.size, "rflscm")), SCHEDULE)
    torch.manual_seed(0)
    model = RFLSCM.build(cfg, device=ctx.device)
    t0 = time.perf_counter()
    fit(model, scenario, progress=False)
    train_s = time.perf_counter() - t0
    t0, c0 = time.perf_counter(), time.process_time()
    model.finish_training()
    finish_s, finish_cpu = time.perf_counter() - t0, time.process_time() - c0
    pairs = int(model._training().data.beam_mask.any(1).sum())
    return model, {
        "preset": ctx.size,
        "schedule": SCHEDULE,
        "train_s": train_s,
        "finish_training_s": finish_s,
        "finish_training_cpu_s": finish_cpu,
        "training_pairs": pairs,
    }


def _patterns(scenario: Scenario, size: str) -> dict[str, np.ndarray]:
    """``{name}_cells``, ``{name}_grids``, ``{name}_xyz`` of the ``by_cell`` and ``mixed`` patterns (seeded)."""
    (num_cells, per_cell), num_mixed = PATTERNS[size]
    cells, grids = scenario.cell_ids(), scenario.grid_ids()
    xyz_of = scenario.grids.set_index("grid_id").loc[:, ["x", "y", "z"]]
    rng = np.random.default_rng(29)
    chosen = cells[np.linspace(0, len(cells) - 1, min(num_cells, len(cells))).round().astype(int)]
    per_cell = min(per_cell, len(grids))
    by_cell = (
        np.repeat(chosen, per_cell),
        np.concatenate([np.sort(rng.choice(grids, per_cell, replace=False)) for _ in chosen]),
    )
    mixed = rng.choice(cells, num_mixed), rng.choice(grids, num_mixed)
    out: dict[str, np.ndarray] = {}
    for name, (c, g) in (("by_cell", by_cell), ("mixed", mixed)):
        out[f"{name}_cells"], out[f"{name}_grids"] = c.astype(np.int64), g.astype(np.int64)
        out[f"{name}_xyz"] = xyz_of.loc[g].to_numpy(np.float64)
    return out


def _worker(src: Path, ckpt: Path, pairs: Path, aps_out: Path, threads: int, profile: bool) -> dict[str, Any]:
    worker = Path(__file__).with_name("render_worker.py")
    cmd = [sys.executable, str(worker), "--checkpoint", str(ckpt), "--pairs", str(pairs), "--aps-out", str(aps_out)]
    cmd += ["--threads", str(threads)] + (["--profile"] if profile else [])
    env = {**os.environ, "PYTHONPATH": str(src), "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads)}
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        tail = (proc.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise RflscmError(f"the render worker ({src}) failed: {tail}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _summary(rows: list[dict[str, Any]], names: list[str]) -> dict[str, Any]:
    out: dict[str, Any] = {
        "setup_s": statistics.median(r["setup_s"] for r in rows),
        "peak_rss_mb": statistics.median(r["peak_rss_mb"] for r in rows),
    }
    for name in names:
        pairs = rows[0][name]["pairs"]
        out[name] = {
            "pairs_per_s": statistics.median(pairs / r[name]["wall_s"] for r in rows),
            "pairs_per_cpu_s": statistics.median(pairs / r[name]["cpu_s"] for r in rows),
            "system_share": statistics.median(r[name]["system_s"] / r[name]["cpu_s"] for r in rows),
            "minor_faults_per_pair": statistics.median(r[name]["minor_faults"] / pairs for r in rows),
            "decoder_evals_per_pair": {k: v / pairs for k, v in rows[0][name].get("decoder_evals", {}).items()},
        }
    return out


def _compare(new: torch.Tensor, ref: torch.Tensor) -> dict[str, Any]:
    """Exact equality and the largest |new − ref| relative to the row's peak of ``ref``."""
    scale = ref.abs().amax(1, keepdim=True).clamp_min(1e-30)
    return {"equal": bool(torch.equal(new, ref)), "max_rel_diff": float(((new - ref).abs() / scale).max())}


def _grad_reference(model: RFLSCM, patterns: dict[str, np.ndarray]) -> dict[str, Any]:
    """The sparse APS of a few ``mixed`` pairs through the inference path (no gradients) against the training
    path (gradients on: the code the trainer runs)."""
    assert model.scene is not None and model.renderer is not None
    cells = torch.as_tensor(model.scene.cell_index(patterns["mixed_cells"][:REFERENCE_PAIRS]))
    xyz = torch.as_tensor(patterns["mixed_xyz"][:REFERENCE_PAIRS], dtype=torch.float32)
    dense = []
    for grad in (False, True):
        with torch.set_grad_enabled(grad):
            bins, values = model.renderer.output(cells, xyz, model.position)
            x = torch.zeros(len(cells), model.angle_grid.num_bins).scatter_add_(1, bins, values.detach())
        dense.append(x)
    return {"pairs": len(cells), **_compare(dense[0], dense[1])}
