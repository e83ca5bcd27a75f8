"""B10 — scale (issue 29): wall time and peak memory of every stage against the network's size.

For each size (a site count; cells = 3 sectors × sites × carriers) B10 runs, one after the other and each in
its own process, the stages a user runs:

* ``simulate``: ``rflscm simulate --backend procedural --sites N`` (the grown city of docs/scale.md: area,
  buildings and grids grow with N; ``--grids`` only when the plan fixes it), once per worker count of ``workers``
  (``simulate@2``: traces and RSRP on 2 Ray workers, into a second folder compared byte for byte with the first,
  ``same_as_first``, then removed when equal);
* ``check``: ``rflscm check`` of that scenario;
* ``train_wnomp``, ``evaluate_wnomp`` and ``optimize_wnomp``: ``rflscm train --model wnomp``, ``rflscm evaluate``
  and ``rflscm optimize`` of it;
* with ``--rflscm-minutes M``, also ``train_rflscm`` (``rflscm train --minutes M``; tiled with ``tile_sites``,
  its tiles on the largest of ``workers``), ``predict_rflscm`` (``--pairs measured``), ``evaluate_rflscm`` and
  ``optimize_rflscm``; each of the last three once per worker count of ``workers`` (``evaluate_rflscm@2`` is the
  2-worker run), so serial and parallel are measured side by side on one checkpoint.

Every stage runs as ``python -m rflscm.cli --threads T …`` with the running package on ``PYTHONPATH`` and the
parent's thread count (``rflscm --threads``); its wall time is the parent's clock around the process and its
peak memory the process's own peak resident set (``ru_maxrss`` of that child from ``os.wait4``: exact, not
sampled).  A stage that fails (an error, or killed for memory) is recorded with its exit status and the
size's later stages are skipped.  Logs are in ``<out>/b10/city<N>/<stage>.log``.

A tiled RF-LSCM's per-tile figures (tiles, training seconds and pairs per tile) are read from its checkpoint's
run information.  Projection: from the largest size's per-cell cost of each stage, the wall time of a network of
``project_cells`` cells at the same density on ``project_machines`` machines like this one
(:func:`project_wall`: linear in cells; the stages that spread — tiles, prediction, evaluation and the optimiser's
rendering — divided over the machines, the others not).

Growth: for each stage with at least two sizes done, the exponent b of time ∝ cellsᵇ and of peak memory ∝
cellsᵇ (least squares in log-log); b ≈ 1 is linear growth in cells.  The memory exponent is also given for
the peak above the first size's peak (the import floor, ~0.35 GB of Python, torch and pandas, hides the
growth at small sizes).  Plot ``b10_scale.png``: time and peak memory vs cells, log-log, one line per stage.
Tables ``b10_scale.csv`` and the JSON of ``rflscm bench``.

Sizes: ``quick`` = 7, 19, 37 sites (42, 114, 222 cells); ``full`` = 7, 19, 37, 167 sites (1 002 cells); ``--sites``
replaces the list.  ``tiny`` (tests) = 1 and 2 sites of the small preset, one carrier, 12 grids per site.
"""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from rflscm.bench import BenchContext, register_bench
from rflscm.bench.report import new_figure, save_figure
from rflscm.errors import ConfigError
from rflscm.runtime import MALLOC_ENV

QUICK_SITES = (7, 19, 37)
FULL_SITES = (7, 19, 37, 167)
STAGES = (
    "simulate",
    "check",
    "train_wnomp",
    "evaluate_wnomp",
    "optimize_wnomp",
    "train_rflscm",
    "predict_rflscm",
    "evaluate_rflscm",
    "optimize_rflscm",
)
SPREAD_STAGES = ("simulate", "train_rflscm", "predict_rflscm", "evaluate_rflscm", "optimize_rflscm")
"""Stages whose work spreads over Ray workers and machines (traces and RSRP per site; tiles; the APS of prediction,
evaluation, optimiser)."""
WORKER_STAGES = ("simulate", "predict_rflscm", "evaluate_rflscm", "optimize_rflscm")
"""Stages run once per worker count of :attr:`B10Plan.workers`.  ``simulate`` with the first count writes the
scenario the other stages read; with another count it writes a second folder, compared with the first file by
file (``same_as_first`` in its row)."""


@dataclass(frozen=True)
class B10Plan:
    """What B10 runs: sizes (site counts) and the options of the stages."""

    sites: tuple[int, ...] = QUICK_SITES
    grids_per_site: int | None = None
    """``--grids`` = this × sites (``None``: the grown city's own grid count, 800 per 7 sites)."""
    scene: str = "city"
    carriers: str | None = None
    """``--carriers`` of simulate (``None``: the default two carriers)."""
    threads: int = 1
    rflscm_minutes: float | None = None
    """Also train RF-LSCM with ``--minutes`` this and evaluate it (``None``: WNOMP only)."""
    tile_sites: int | None = None
    """Train RF-LSCM in tiles of about this many sites (``--tile-sites``; ``None``: one model)."""
    workers: tuple[int, ...] = (1,)
    """Worker counts of the parallel stages (:data:`WORKER_STAGES`); a tiled training uses the largest."""
    project_cells: int = 10_000
    project_machines: tuple[int, ...] = (1, 8, 64)
    given: dict[int, str] = field(default_factory=dict)
    """Site count → a scenario folder simulated before (by the same ``simulate`` command): that size's
    ``simulate`` stage is not run again (its row says so) and the other stages read that folder."""
    predict: bool = True
    """Run the ``predict_rflscm`` stages (``--pairs measured``; the evaluation renders its own pairs anyway)."""
    optimize_sites: int | None = None
    """The optimiser changes only the cells of this many sites nearest the network's centre (``--cells``, a
    cluster; ``None``: every cell)."""
    timeout_s: float | None = None
    """A stage running longer is stopped and recorded as failed (``None``: no limit)."""
    extra: dict[str, tuple[str, ...]] = field(default_factory=dict)
    """Extra arguments per stage (tests: smaller RF-LSCM settings)."""

    def __post_init__(self) -> None:
        if not self.sites or any(int(n) < 1 for n in self.sites):
            raise ConfigError("b10: --sites needs one or more site counts >= 1, e.g. --sites 7,19,37.")
        if self.rflscm_minutes is not None and not self.rflscm_minutes > 0:
            raise ConfigError(f"b10: --rflscm-minutes must be > 0 (got {self.rflscm_minutes}).")
        if self.tile_sites is not None and int(self.tile_sites) < 1:
            raise ConfigError(f"b10: tile_sites must be >= 1 (got {self.tile_sites}).")
        if not self.workers or any(int(w) < 1 for w in self.workers):
            raise ConfigError(f"b10: workers must be one or more counts >= 1 (got {list(self.workers)}).")
        if self.optimize_sites is not None and int(self.optimize_sites) < 1:
            raise ConfigError(f"b10: optimize_sites must be >= 1 (got {self.optimize_sites}).")
        if int(self.project_cells) < 1 or not self.project_machines or any(int(m) < 1 for m in self.project_machines):
            raise ConfigError("b10: project_cells and project_machines must be >= 1.")


def _package_src() -> str:
    import rflscm

    return str(Path(rflscm.__file__).resolve().parents[1])


def run_stage(cmd: list[str], log: Path, timeout_s: float | None = None) -> dict[str, Any]:
    """Run ``cmd`` (output to ``log``) and return its exit status, wall time [s] and peak RSS [MB] (the child's
    own ``ru_maxrss``, from ``os.wait4``)."""
    path = os.pathsep.join([_package_src(), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))])
    env = {**os.environ, **MALLOC_ENV, "PYTHONPATH": path, "COLUMNS": "120"}
    log.parent.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    with open(log, "w") as fh:
        proc = subprocess.Popen(cmd, env=env, stdout=fh, stderr=subprocess.STDOUT)
        status, usage = _wait(proc, timeout_s)
    wall = time.perf_counter() - start
    rc = os.waitstatus_to_exitcode(status) if status is not None else 124
    return {"rc": rc, "wall_s": wall, "peak_rss_mb": usage.ru_maxrss / 1024.0 if usage is not None else None}


def _wait(proc: subprocess.Popen, timeout_s: float | None) -> tuple[int | None, Any]:
    """``os.wait4`` on ``proc`` (polling when there is a time limit; the child is killed past it)."""
    deadline = None if timeout_s is None else time.monotonic() + timeout_s
    while True:
        pid, status, usage = os.wait4(proc.pid, 0 if deadline is None else os.WNOHANG)
        if pid == proc.pid:
            proc.returncode = os.waitstatus_to_exitcode(status)
            return status, usage
        if deadline is not None and time.monotonic() > deadline:
            proc.kill()
            _, status, usage = os.wait4(proc.pid, 0)
            proc.returncode = 124
            return None, usage
        time.sleep(0.2)


def _commands(plan: B10Plan, sites: int, folder: Path) -> dict[str, list[str]]:
    cli = [sys.executable, "-m", "rflscm.cli", "--threads", str(plan.threads)]
    scen = str(plan.given.get(sites, folder / "scenario"))
    sim = [*cli, "simulate", "--backend", "procedural", "--scene", plan.scene, "--sites", str(sites)]
    sim += ["--no-progress", "--force", "--device", "cpu"]
    if plan.grids_per_site is not None:
        sim += ["--grids", str(plan.grids_per_site * sites)]
    if plan.carriers is not None:
        sim += ["--carriers", plan.carriers]
    quiet = ["--no-progress", "--device", "cpu", "--force"]
    wn = str(folder / "wnomp.ckpt")
    commands: dict[str, list[str]] = {}
    for i, w in enumerate(plan.workers):
        out = scen if i == 0 else str(_second_scenario(folder, w))
        commands["simulate" + ("" if i == 0 else f"@{w}")] = [*sim, "--out", out, "--workers", str(w)]
    commands.update(
        {
            "check": [*cli, "check", scen],
            "train_wnomp": [*cli, "train", scen, "--model", "wnomp", "--out", wn, *quiet],
            "evaluate_wnomp": [*cli, "evaluate", wn, scen, "--device", "cpu", "--force"],
            "optimize_wnomp": [
                *cli,
                "optimize",
                wn,
                scen,
                "--out",
                str(folder / "opt_wnomp"),
                "--device",
                "cpu",
                "--force",
            ],
        }
    )
    commands["evaluate_wnomp"] += ["--json", str(folder / "wnomp_eval.json")]
    if plan.rflscm_minutes is not None:
        rf = str(folder / "rflscm.ckpt")
        budget = ["--minutes", f"{plan.rflscm_minutes:g}"]
        train = [*cli, "train", scen, "--model", "rflscm", "--out", rf, *budget, *quiet]
        if plan.tile_sites is not None:
            train += ["--tile-sites", str(plan.tile_sites), "--workers", str(max(plan.workers))]
        commands["train_rflscm"] = train
        for w in plan.workers:
            tag = "" if w == 1 else f"@{w}"
            par = ["--workers", str(w)] if w != 1 else []
            if plan.predict:
                commands[f"predict_rflscm{tag}"] = [
                    *[*cli, "predict", rf, scen, "--pairs", "measured", "--device", "cpu", "--force"],
                    *["--out", str(folder / f"predict{tag.replace('@', '_w')}.parquet"), *par],
                ]
            commands[f"evaluate_rflscm{tag}"] = [
                *[*cli, "evaluate", rf, scen, "--device", "cpu", "--force"],
                *["--json", str(folder / f"rflscm_eval{tag.replace('@', '_w')}.json"), *par],
            ]
            commands[f"optimize_rflscm{tag}"] = [
                *[*cli, "optimize", rf, scen, "--out", str(folder / f"opt_rflscm{tag.replace('@', '_w')}")],
                *["--device", "cpu", "--force", *par],
            ]
    for stage, args in plan.extra.items():
        for name in commands:
            if name.split("@")[0] == stage:
                commands[name] = [*commands[name], *args]
    order = {stage: i for i, stage in enumerate(STAGES)}
    return dict(sorted(commands.items(), key=lambda kv: order[kv[0].split("@")[0]]))


def _second_scenario(folder: Path, workers: int) -> Path:
    """Where ``simulate`` with a worker count other than the plan's first writes its scenario."""
    return folder / f"scenario_w{workers}"


def same_files(a: Path, b: Path) -> bool:
    """True when folders ``a`` and ``b`` hold the same files with the same bytes."""
    names = [sorted(str(p.relative_to(f)) for p in f.rglob("*") if p.is_file()) for f in (a, b)]
    if names[0] != names[1]:
        return False
    for name in names[0]:
        with open(a / name, "rb") as fa, open(b / name, "rb") as fb:
            while True:
                x, y = fa.read(1 << 20), fb.read(1 << 20)
                if x != y:
                    return False
                if not x:
                    break
    return True


def _scenario_size(scen: Path) -> dict[str, int]:
    """Cells, grids and measurement rows of a written scenario (Parquet footers only)."""
    import pyarrow.parquet as pq  # type: ignore[import-untyped]

    def rows(name: str) -> int:
        path = scen / name
        return int(pq.ParquetFile(path).metadata.num_rows) if path.is_file() else 0

    return {
        "cells": rows("cells_round1.parquet"),
        "grids": rows("grids.parquet"),
        "measurement_rows": rows("measurements.parquet"),
        "path_rows": rows("truth/paths.parquet"),
    }


def growth_exponent(cells: list[float], values: list[float]) -> float | None:
    """b of ``values ∝ cellsᵇ`` (least squares in log-log) over the positive pairs; ``None`` under two sizes."""
    pts = [(math.log(c), math.log(v)) for c, v in zip(cells, values, strict=True) if c > 0 and v and v > 0]
    if len({p[0] for p in pts}) < 2:
        return None
    x, y = np.array([p[0] for p in pts]), np.array([p[1] for p in pts])
    return float(np.polyfit(x, y, 1)[0])


def run_b10(plan: B10Plan, out_dir: Path) -> dict[str, Any]:
    """Run the plan's stages at every size; rows per (size, stage) and the growth per stage."""
    root = Path(out_dir) / "b10"
    rows: list[dict[str, Any]] = []
    sizes: list[dict[str, Any]] = []
    for sites in plan.sites:
        folder = root / f"city{sites}"
        size: dict[str, Any] = {"sites": int(sites)}
        failed = None
        scen = Path(plan.given.get(int(sites), folder / "scenario"))
        for stage, cmd in _commands(plan, int(sites), folder).items():
            if stage.startswith("simulate") and int(sites) in plan.given:
                if stage == "simulate":
                    size.update(_scenario_size(scen))
                    rows.append(
                        {"sites": int(sites), "stage": stage, "status": f"given ({scen})", "command": _shown(cmd)}
                    )
                continue
            if stage.startswith("optimize") and plan.optimize_sites is not None and failed is None:
                cluster = central_cells(scen, int(plan.optimize_sites))
                cmd = [*cmd, "--cells", ",".join(map(str, cluster))]
                size["optimize_cells"] = len(cluster)
            if failed is not None:
                rows.append({"sites": int(sites), "stage": stage, "status": f"skipped ({failed} failed)"})
                continue
            result = run_stage(cmd, folder / f"{stage}.log", plan.timeout_s)
            if stage == "simulate" and result["rc"] == 0:
                size.update(_scenario_size(scen))
            if stage.startswith("simulate@") and result["rc"] == 0:
                second = _second_scenario(folder, int(stage.split("@")[1]))
                result["same_as_first"] = same_files(scen, second)
                if result["same_as_first"]:  # a copy: free its disk (kept where it differs, to look at)
                    shutil.rmtree(second, ignore_errors=True)
            if stage == "train_rflscm" and result["rc"] == 0:
                size.update(_tile_figures(folder / "rflscm.ckpt"))
            status = "ok" if result["rc"] == 0 else f"failed (exit {result['rc']})"
            if result["rc"] != 0:
                failed = stage
            rows.append({"sites": int(sites), "stage": stage, "status": status, **result, "command": _shown(cmd)})
            _save_progress(root, rows, [*sizes, size])
        sizes.append(size)
    cells_of = {s["sites"]: s.get("cells", 0) for s in sizes}
    for row in rows:
        row["cells"] = cells_of.get(row["sites"], 0)
    growth: dict[str, Any] = {}
    for stage in dict.fromkeys(r["stage"] for r in rows):
        done = [r for r in rows if r["stage"] == stage and r.get("status") == "ok" and r["cells"] > 0]
        if len(done) < 2:
            continue
        cells = [float(r["cells"]) for r in done]
        peaks = [float(r["peak_rss_mb"]) for r in done]
        growth[stage] = {
            "time_exponent": growth_exponent(cells, [float(r["wall_s"]) for r in done]),
            "memory_exponent": growth_exponent(cells, peaks),
            "memory_above_first_exponent": growth_exponent(cells[1:], [p - peaks[0] for p in peaks[1:]])
            if len(done) >= 3
            else None,
        }
    _write_csv(root / "b10_scale.csv", rows)
    plot = _plot(rows, root)
    projection = project_wall(rows, plan.project_cells, plan.project_machines)
    return {
        "plan": _plan_dict(plan),
        "sizes": sizes,
        "stages": rows,
        "growth": growth,
        "projection": projection,
        "plot": plot,
    }


def central_cells(scenario: Path, sites: int) -> list[int]:
    """Cell ids of the ``sites`` sites nearest the centre of the scenario's sites (round 1's cells table)."""
    from rflscm.data.io import read_table

    cells = read_table(scenario / "cells_round1.parquet")  # what `rflscm simulate` writes
    pos = cells.groupby("site_id")[["x", "y"]].first()
    centre = pos.mean().to_numpy()
    dist = np.hypot(pos["x"].to_numpy() - centre[0], pos["y"].to_numpy() - centre[1])
    chosen = pos.index.to_numpy()[np.argsort(dist, kind="stable")[:sites]]
    return sorted(int(c) for c in cells.loc[cells["site_id"].isin(chosen), "cell_id"])


def _tile_figures(ckpt: Path) -> dict[str, Any]:
    """Tiles and per-tile training seconds and pairs of a tiled checkpoint (empty for one model)."""
    from rflscm.models.base import read_checkpoint

    info = read_checkpoint(ckpt).get("run_info", {})
    fits = info.get("tile_fits") or []
    if not fits:
        return {}
    seconds = [float(f["seconds"]) for f in fits]
    pairs = [int(f["pairs"]) for f in fits]
    return {
        "tiles": len(fits),
        "tile_seconds_mean": float(np.mean(seconds)),
        "tile_seconds_max": float(max(seconds)),
        "tile_pairs_mean": float(np.mean(pairs)),
        "tile_pairs_max": int(max(pairs)),
    }


def project_wall(rows: list[dict[str, Any]], cells: int, machines: tuple[int, ...]) -> dict[str, Any]:
    """Wall time [s] of each stage on a network of ``cells`` cells (same density) on each machine count.

    From the largest size measured, per stage: its wall time per cell × ``cells`` (growth linear in cells, which
    B10's exponents check), divided by the machine count for :data:`SPREAD_STAGES` (each machine runs tiles or
    APS chunks like this one did; its serial driver part is counted in) and not divided for the others (one
    process).  A worker-count variant is projected from its own row.  Returns per stage and machine count the
    seconds, and the basis (cells and wall time measured)."""
    done = [r for r in rows if r.get("status") == "ok" and r.get("cells", 0) > 0]
    if not done:
        return {}
    out: dict[str, Any] = {"cells": int(cells), "machines": [int(m) for m in machines], "stages": {}}
    for stage in dict.fromkeys(r["stage"] for r in done):
        largest = max((r for r in done if r["stage"] == stage), key=lambda r: r["cells"])
        per_cell = float(largest["wall_s"]) / float(largest["cells"])
        spread = stage.split("@")[0] in SPREAD_STAGES
        out["stages"][stage] = {
            "from_cells": int(largest["cells"]),
            "from_wall_s": float(largest["wall_s"]),
            "spread": spread,
            "wall_s": {str(m): per_cell * cells / (m if spread else 1) for m in machines},
        }
    return out


def _shown(cmd: list[str]) -> str:
    return " ".join(["rflscm", *cmd[3:]])


def _plan_dict(plan: B10Plan) -> dict[str, Any]:
    return {
        "sites": list(plan.sites),
        "grids_per_site": plan.grids_per_site,
        "scene": plan.scene,
        "carriers": plan.carriers,
        "threads": plan.threads,
        "rflscm_minutes": plan.rflscm_minutes,
        "tile_sites": plan.tile_sites,
        "workers": list(plan.workers),
        "project_cells": plan.project_cells,
        "project_machines": list(plan.project_machines),
        "optimize_sites": plan.optimize_sites,
        "given": {str(k): v for k, v in plan.given.items()},
        "predict": plan.predict,
    }


def _save_progress(root: Path, rows: list[dict[str, Any]], sizes: list[dict[str, Any]]) -> None:
    """The rows so far (a long run that is stopped keeps what it measured)."""
    root.mkdir(parents=True, exist_ok=True)
    (root / "b10_partial.json").write_text(json.dumps({"sizes": sizes, "stages": rows}, indent=2, default=float))


def _write_csv(path: Path, rows: list[dict[str, Any]]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    keys = ["sites", "cells", "stage", "status", "wall_s", "peak_rss_mb", "command"]
    with open(path, "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=keys, extrasaction="ignore")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: row.get(k, "") for k in keys})


def _plot(rows: list[dict[str, Any]], root: Path) -> str | None:
    done = [r for r in rows if r.get("status") == "ok" and r.get("cells", 0) > 0]
    if not done:
        return None
    fig, (ax_t, ax_m) = new_figure(2)
    for stage in dict.fromkeys(r["stage"] for r in done):
        pts = sorted((r["cells"], r["wall_s"], r["peak_rss_mb"]) for r in done if r["stage"] == stage)
        if not pts:
            continue
        cells = [p[0] for p in pts]
        ax_t.plot(cells, [p[1] for p in pts], marker="o", label=stage)
        ax_m.plot(cells, [p[2] / 1024.0 for p in pts], marker="o", label=stage)
    for ax, label in ((ax_t, "wall time [s]"), (ax_m, "peak memory (RSS) [GB]")):
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("cells [count]")
        ax.set_ylabel(label)
        ax.grid(True, which="both", alpha=0.3)
    fig.subplots_adjust(wspace=0.35)
    ax_t.legend(fontsize=7)
    ax_t.set_title("B10: time per stage vs network size")
    ax_m.set_title("B10: peak memory per stage vs network size")
    ctx = BenchContext(size="", seeds=1, out_dir=root, device="cpu", scenario=None)
    return save_figure(fig, ctx, "b10_scale")


PLAN_KEYS = (
    "sites",
    "grids_per_site",
    "scene",
    "carriers",
    "rflscm_minutes",
    "timeout_s",
    "tile_sites",
    "workers",
    "project_cells",
    "project_machines",
    "optimize_sites",
    "given",
    "predict",
    "extra",
)
"""Keys of a ``--config`` YAML of B10 (the :class:`B10Plan` fields; the command line's --sites and
--rflscm-minutes win)."""


def plan_of(ctx: BenchContext) -> B10Plan:
    """The plan of ``rflscm bench b10``: ``--config`` YAML (keys :data:`PLAN_KEYS`), then ``--sites`` and
    ``--rflscm-minutes``; sites default to the size's list; threads are the parent's."""
    import torch

    from rflscm.config import load_yaml

    given: dict[str, Any] = {}
    if ctx.config is not None:
        data = load_yaml(ctx.config)
        if not isinstance(data, dict):
            raise ConfigError(f"{ctx.config}: a B10 config is a mapping of {', '.join(PLAN_KEYS)}.")
        unknown = sorted(set(data) - set(PLAN_KEYS))
        if unknown:
            raise ConfigError(f"{ctx.config}: unknown B10 key(s) {', '.join(unknown)}; valid: {', '.join(PLAN_KEYS)}.")
        given = dict(data)
    if ctx.sites:
        given["sites"] = ctx.sites
    if ctx.minutes is not None:
        given["rflscm_minutes"] = ctx.minutes
    sites = given.pop("sites", None) or (FULL_SITES if ctx.size == "full" else QUICK_SITES)
    for key in ("workers", "project_machines"):
        if key in given:
            given[key] = tuple(int(v) for v in given[key])
    if "given" in given:
        folders = given["given"]
        if not isinstance(folders, dict):
            raise ConfigError("b10 config: `given` maps a site count to a scenario folder simulated before.")
        for folder in folders.values():
            if not (Path(str(folder)) / "scenario.yaml").is_file():
                raise ConfigError(f"b10 config: `given` folder {folder} has no scenario.yaml.")
        given["given"] = {int(k): str(v) for k, v in folders.items()}
    if "extra" in given:
        extra = given["extra"]
        if not isinstance(extra, dict) or not all(isinstance(v, list) for v in extra.values()):
            raise ConfigError("b10 config: `extra` maps a stage name to a list of extra arguments.")
        unknown = sorted(set(extra) - set(STAGES))
        if unknown:
            raise ConfigError(f"b10 config: `extra` names unknown stage(s) {', '.join(unknown)}.")
        given["extra"] = {k: tuple(str(a) for a in v) for k, v in extra.items()}
    try:
        return B10Plan(sites=tuple(int(s) for s in sites), threads=torch.get_num_threads(), **given)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"b10 config: {exc}.") from None


@register_bench(
    "b10", "Scale: time and peak memory of simulate, check, train, predict, evaluate and optimize vs network size"
)
def bench_b10(ctx: BenchContext) -> dict[str, Any]:
    if ctx.scenario is not None:
        raise ConfigError("b10 simulates its own procedural networks; drop --scenario (give --sites instead).")
    return run_b10(plan_of(ctx), ctx.out_dir)
