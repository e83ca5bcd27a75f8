"""Why the CLI sets OMP_WAIT_POLICY=PASSIVE: small torch ops with spinning OpenMP threads on a busy machine.

Starts one busy-looping process per CPU core (the "other job"), then times 300 small forward/backward
steps in a fresh interpreter with torch's defaults, with OMP_NUM_THREADS=1, and with
OMP_WAIT_POLICY=PASSIVE, and prints the seconds of each.

Usage: python experiments/omp_contention.py [HOGS]   (HOGS defaults to the number of cores; about a minute)
"""

from __future__ import annotations

import multiprocessing as mp
import os
import subprocess
import sys
import time

WORK = """
import time, torch
x = torch.randn(20_000, 16, requires_grad=True)
t = time.perf_counter()
for _ in range(300):
    y = (torch.exp(x * 0.5) + x.sin()).cumsum(0)[::3].sum()
    y.backward()
print(f"{time.perf_counter() - t:.2f}")
"""


def _spin(stop: float) -> None:
    while time.time() < stop:
        pass


def main(hogs: int) -> None:
    variants = {
        "torch defaults": {},
        "OMP_NUM_THREADS=1": {"OMP_NUM_THREADS": "1"},
        "OMP_WAIT_POLICY=PASSIVE": {"OMP_WAIT_POLICY": "PASSIVE"},
    }
    procs = [mp.Process(target=_spin, args=(time.time() + 600,), daemon=True) for _ in range(hogs)]
    for p in procs:
        p.start()
    try:
        for name, extra in variants.items():
            env = {k: v for k, v in os.environ.items() if k not in ("OMP_NUM_THREADS", "OMP_WAIT_POLICY")}
            out = subprocess.run(
                [sys.executable, "-c", WORK], env={**env, **extra}, capture_output=True, text=True, check=True
            )
            print(f"{name:26s} {out.stdout.strip():>7s} s   ({hogs} busy processes beside it)", flush=True)
    finally:
        for p in procs:
            p.terminate()


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else os.cpu_count() or 1)
