"""One RF-LSCM variant on the B1 quick subset: validation-MAE curve and round-2 MAE (the tuning runs of
BENCHMARKS.md, "RF-LSCM tuning").

Usage:
    python experiments/tune_rflscm.py TAG STEPS ['{"decoder": {"hidden": 128}, "_warmup": 600}']

The JSON holds config overrides laid over the quick preset and the bench's quick size;
``_warmup`` sets the HiTAM warm-up (default two thirds of STEPS; the ramp is a tenth of STEPS) and
``_seed`` the training seed (default 0).
One thread, so that two or three variants can run side by side on 2 cores.  Prints the curve
every tenth of the run and a final ``TAG RESULT {json}`` line.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import torch

from rflscm.bench import BenchContext
from rflscm.bench.harness import load_bench_data, merge, quick_size, train_and_evaluate


def main(tag: str, steps: int, overrides: dict) -> None:
    torch.set_num_threads(1)
    data = load_bench_data(BenchContext("quick", 1, Path("out/tune"), "cpu", None), quick_size())
    warmup = int(overrides.pop("_warmup", 2 * steps // 3))
    seed = int(overrides.pop("_seed", 0))
    every = max(steps // 10, 1)
    base = {"train": {"steps": steps, "val_every": every}, "hitam": {"warmup_steps": warmup, "ramp_steps": every}}
    curve: list[tuple[int, float, float]] = []

    def on_step(model, row: dict) -> None:
        if row["step"] % every == 0:
            curve.append((int(row["step"]), round(row["time_s"], 1), round(row["val_mae_db"], 2)))
            print(tag, curve[-1], flush=True)

    run = train_and_evaluate(data, "rflscm", extra=merge(base, overrides), seed=seed, on_step=on_step)
    mae = run.metrics["mae_db"]
    result = {"ssb": mae["ssb"], "csi": mae["csi"], "train_s": round(run.train_time_s), "curve": curve}
    print(tag, "RESULT", json.dumps(result), flush=True)


if __name__ == "__main__":
    main(sys.argv[1], int(sys.argv[2]), json.loads(sys.argv[3]) if len(sys.argv) > 3 else {})
