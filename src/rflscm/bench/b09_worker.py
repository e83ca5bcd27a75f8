"""B9's worker: train one RF-LSCM and record its round-2 MAE at marks of training time (a standalone script).

B9 (:mod:`rflscm.bench.b09_time_to_target`) runs this file *by path* in a subprocess, once with
``PYTHONPATH`` at an exported older commit's ``src`` and once at the current package's ``src``, so
it uses only what both have: ``rflscm.data.load_scenario``, ``rflscm.geometry.AngleGrid``,
``rflscm.models.MODEL_REGISTRY["rflscm"].build``, ``rflscm.models.rflscm.config.preset_path``,
``rflscm.bench.harness.merge``,
``rflscm.eval.protocols.AdjustProtocol`` / ``fit_with_protocol`` (whose callback gets the metrics
of every step) and ``rflscm.eval.run_evaluation``.  It is never imported as part of ``rflscm``.

Training time counts from the call of ``fit_with_protocol`` (data preparation included); every
evaluation's wall time (and CPU time) is taken off, so ``train_s`` is training alone.  Before each
evaluation the model's ``finish_training`` runs (where it has one: the post-training measurements a
saved checkpoint carries); its time is added to that row's ``train_s`` (and given as ``finish_s``) but
not to later rows', so every row is the time to a model as ``rflscm train`` would save it at that point.  When
``train_s`` passes a mark the model is evaluated (adjust protocol, no oracle) and one row is
written; once more at the end of the schedule or when ``--max-seconds`` stops the run.

Usage: ``python b09_worker.py --scenario DIR --config quick --out rows.json [--overrides JSON]
[--angle-grid 91,72,-90,2] [--marks 5,10,20] [--max-seconds S] [--threads N] [--seed N] [--device cpu]``.
"""

from __future__ import annotations

import sys
from pathlib import Path

# run by path, Python puts this folder first on sys.path; drop it so that its modules cannot shadow others
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if (Path(p).resolve() if p else Path.cwd().resolve()) != _HERE]

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import random  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402


class _Stop(Exception):
    """Raised from the training callback when ``--max-seconds`` of training time are spent."""


def _config(spec: str, overrides: dict[str, Any]) -> Any:
    """The preset name or YAML path as given, or (with overrides) its mapping with the overrides laid over."""
    if not overrides:
        return spec
    from rflscm.bench.harness import merge
    from rflscm.config import load_yaml
    from rflscm.models.rflscm.config import preset_path

    path = Path(spec) if Path(spec).is_file() else preset_path(spec, "rflscm")
    return merge(load_yaml(path), overrides)  # strict keys, bounded aliases, regular files only


def _number(value: Any) -> float | None:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) else None


def _block(metrics: dict[str, Any], key: str) -> dict[str, dict[str, float | None]] | None:
    from rflscm.data import BEAM_TYPES  # the code under test's, imported once PYTHONPATH has picked it

    block = metrics.get(key)
    if not isinstance(block, dict):
        return None
    return {bt: {k: _number((block.get(bt) or {}).get(k)) for k in ("all", "changed")} for bt in BEAM_TYPES}


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", required=True)
    p.add_argument("--config", default="quick", help="preset name or YAML path")
    p.add_argument("--overrides", default="{}", help="JSON mapping laid over the config")
    p.add_argument("--angle-grid", default="", help="num_el,num_az,el_min_deg,el_step_deg (default: AngleGrid())")
    p.add_argument("--marks", default="", help="training seconds at which to evaluate, comma-separated")
    p.add_argument("--max-seconds", type=float, default=None)
    p.add_argument("--minutes", type=float, default=None, help="train to this budget (new code only: `budget_s`)")
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--device", default="cpu")
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)

    import numpy as np
    import torch

    import rflscm
    from rflscm.data import load_scenario
    from rflscm.eval import run_evaluation
    from rflscm.eval.protocols import AdjustProtocol, fit_with_protocol
    from rflscm.geometry import AngleGrid
    from rflscm.models import MODEL_REGISTRY

    if args.threads:
        torch.set_num_threads(args.threads)
    random.seed(args.seed)
    np.random.seed(args.seed % 2**32)
    torch.manual_seed(args.seed)
    cuda = args.device.startswith("cuda")
    marks = sorted(float(m) for m in args.marks.split(",") if m.strip())
    grid = AngleGrid()
    if args.angle_grid:
        el, az, lo, step = args.angle_grid.split(",")
        grid = AngleGrid(int(el), int(az), float(lo), float(step))

    scenario = load_scenario(args.scenario)
    config = _config(args.config, json.loads(args.overrides))
    model = MODEL_REGISTRY["rflscm"].build(config, grid, args.device)
    rows: list[dict[str, Any]] = []
    excluded = {"wall": 0.0, "cpu": 0.0}
    state = {"next": 0, "step": 0}
    start = {"wall": 0.0, "cpu": 0.0}

    def clocks() -> tuple[float, float]:
        if cuda:
            torch.cuda.synchronize()
        return time.perf_counter(), time.process_time()

    def finish_clocks() -> tuple[float, float]:
        """Run the model's ``finish_training`` (where it has one); its wall and CPU seconds, which count for this row
        alone (a run that goes on does not pay them)."""
        finish = getattr(model, "finish_training", None)
        if finish is None:
            return 0.0, 0.0
        wall, cpu = clocks()
        finish()
        wall2, cpu2 = clocks()
        excluded["wall"] += wall2 - wall
        excluded["cpu"] += cpu2 - cpu
        return wall2 - wall, cpu2 - cpu

    def evaluate(step: int, finish_s: tuple[float, float] = (0.0, 0.0)) -> None:
        wall, cpu = clocks()
        row: dict[str, Any] = {
            "step": step,
            "train_s": wall - start["wall"] - excluded["wall"] + finish_s[0],
            "cpu_s": cpu - start["cpu"] - excluded["cpu"] + finish_s[1],
            "finish_s": finish_s[0],
        }
        metrics = run_evaluation(model, scenario, AdjustProtocol(), oracle=None, max_aps_pairs=0).metrics
        row["mae_db"] = _block(metrics, "mae_db")
        row["bias_db"] = _block(metrics, "bias_db")
        wall2, cpu2 = clocks()
        row["eval_s"] = wall2 - wall
        excluded["wall"] += wall2 - wall
        excluded["cpu"] += cpu2 - cpu
        rows.append(row)
        print(f"b9 worker: step {step}, {row['train_s']:.1f} s training, mae {row['mae_db']}", flush=True)

    def callback(metrics: dict[str, float]) -> None:
        step = int(metrics["step"])
        state["step"] = step
        wall, _ = clocks()
        train_s = wall - start["wall"] - excluded["wall"]
        due = False
        while state["next"] < len(marks) and train_s >= marks[state["next"]]:
            state["next"] += 1
            due = True
        over = args.max_seconds is not None and train_s >= args.max_seconds
        if due or over:
            evaluate(step, finish_clocks())
        if over:
            raise _Stop

    stopped = "schedule"
    start["wall"], start["cpu"] = clocks()
    try:
        if args.minutes is None:
            fit_with_protocol(model, scenario, AdjustProtocol(), progress=False, callback=callback)
        else:  # the budget's clock leaves the evaluations out, as train_s does
            fit_with_protocol(
                model,
                scenario,
                AdjustProtocol(),
                progress=False,
                callback=callback,
                budget_s=60.0 * args.minutes,
                clock=lambda: clocks()[0] - excluded["wall"],
            )
    except _Stop:
        stopped = "max_seconds"
    if not rows or rows[-1]["step"] != state["step"]:
        evaluate(state["step"])
    cfg: Any = getattr(model, "config", None)
    result = {
        "rflscm_file": str(Path(rflscm.__file__).resolve()),
        "rflscm_version": getattr(rflscm, "__version__", None),
        "config": args.config,
        "overrides": json.loads(args.overrides),
        "model_config": dataclasses.asdict(cfg)
        if dataclasses.is_dataclass(cfg) and not isinstance(cfg, type)
        else None,
        "steps_planned": getattr(getattr(cfg, "train", None), "steps", None),
        "budget_minutes": args.minutes,
        "steps_done": state["step"],
        "stopped_by": stopped,
        "threads": torch.get_num_threads(),
        "device": args.device,
        "seed": args.seed,
        "marks_s": marks,
        "max_seconds": args.max_seconds,
        "rows": rows,
    }
    Path(args.out).write_text(json.dumps(result, indent=2, default=str))


if __name__ == "__main__":
    main()
