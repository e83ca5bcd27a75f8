"""Benchmark: WNOMP throughput, (cell, grid) problems per second (target ≥ 3000/s with M = 40, N = 6552
on 2 CPU cores).

The problems are realistic: a cell's real sensing matrix (8 SSB + 32 CSI-RS beams of the default
8 × 4 array at 3.5 GHz on the 91 × 72 angle grid), APS of 1…6 paths spread over 30 dB, and RSRP
with 2 dB noise, 1 dB quantisation and the −120 dBm reporting threshold.  The timed code path is
the one :meth:`WNOMPModel.fit` runs (chunks over the worker threads), without the data loading.
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import torch

from rflscm.antenna import CellAntenna, DFTCodebook, SSBCodebook, sensing_matrix, wavelength_of
from rflscm.bench import BenchContext, register_bench
from rflscm.geometry import AngleGrid
from rflscm.models.wnomp import CellMatrices, WNOMPConfig, _num_cores, solve_jobs

TARGET_PER_S = 3000.0


def _angle_grid(num_bins: int) -> AngleGrid:
    if num_bins == AngleGrid().num_bins:
        return AngleGrid()
    if num_bins % 72 == 0 and num_bins // 72 >= 2:
        return AngleGrid.full_sphere(num_bins // 72, 72)
    return AngleGrid.full_sphere(num_bins, 1) if num_bins >= 2 else AngleGrid(1, 1)


def sensing_for(num_beams: int, grid: AngleGrid) -> torch.Tensor:
    """``A [num_beams, num_bins]``: SSB + CSI-RS rows of one cell, repeated with other azimuths past 40 beams."""
    wl = wavelength_of(3.5e9)
    parts: list[torch.Tensor] = []
    azimuth = 120.0
    while sum(p.shape[0] for p in parts) < num_beams:
        antenna = CellAntenna(azimuth_deg=azimuth, mech_tilt_deg=4.0, elec_tilt_deg=2.0)
        parts += [sensing_matrix(antenna, SSBCodebook(), grid, wl), sensing_matrix(antenna, DFTCodebook(), grid, wl)]
        azimuth += 37.0
    return torch.cat(parts)[:num_beams].contiguous()


def synthetic_rsrp_mw(a: torch.Tensor, num_problems: int, seed: int = 0) -> np.ndarray:
    """RSRP [mW] ``[num_problems, num_beams]`` (NaN below −120 dBm) of random sparse APS seen through ``a``."""
    rng = np.random.default_rng(seed)
    num_beams, num_bins = a.shape
    num_paths = rng.integers(1, 7, num_problems)
    x = np.zeros((num_problems, num_bins))
    for i, k in enumerate(num_paths):
        x[i, rng.choice(num_bins, k, replace=False)] = 10.0 ** (-rng.uniform(10.0, 13.0, k))
    rsrp_dbm = 10.0 * np.log10(x @ a.double().numpy().T) + rng.normal(0.0, 2.0, (num_problems, num_beams))
    rsrp_dbm = np.round(rsrp_dbm)
    rsrp_dbm[rsrp_dbm < -120.0] = np.nan
    return 10.0 ** (rsrp_dbm / 10.0)


def run_wnomp_speed(
    num_problems: int,
    num_beams: int = 40,
    num_bins: int = 6552,
    config: WNOMPConfig | None = None,
    device: str = "cpu",
    repeats: int = 3,
) -> dict[str, Any]:
    """Time WNOMP on ``num_problems`` synthetic (cell, grid) problems; best of ``repeats`` runs.

    Returns a JSON-able dict: ``problems_per_s`` (wall), ``problems_per_cpu_s`` (process CPU time, all
    threads), ``seconds``, ``workers``, ``mean_atoms``, ``target_problems_per_s``, ``meets_target``.
    """
    config = config or WNOMPConfig()
    grid = _angle_grid(num_bins)
    a = sensing_for(num_beams, grid).to(device)
    rsrp_mw = synthetic_rsrp_mw(a.cpu(), num_problems)
    chunk = config.chunk_size
    jobs = [
        (0, np.arange(s, min(s + chunk, num_problems)), rsrp_mw[s : s + chunk]) for s in range(0, num_problems, chunk)
    ]
    best: dict[str, float] = {}
    atoms = 0.0
    for _ in range(repeats):
        matrices = CellMatrices(lambda cell: a)
        for _job in jobs:
            matrices.expect(0)
        wall, cpu = time.perf_counter(), time.process_time()
        out = list(solve_jobs(jobs, matrices, config, None, torch.device(device)))
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        if not best or wall < best["seconds"]:
            best = {"seconds": wall, "cpu_seconds": cpu}
        atoms = float(np.concatenate([(idx >= 0).sum(1) for _, idx, _ in out]).mean())
    per_s = num_problems / best["seconds"]
    return {
        "num_problems": num_problems,
        "num_beams": int(a.shape[0]),
        "num_bins": grid.num_bins,
        "k_max": config.k_max,
        "workers": 1 if device != "cpu" else (config.num_workers or _num_cores()),
        "seconds": best["seconds"],
        "cpu_seconds": best["cpu_seconds"],
        "problems_per_s": per_s,
        "problems_per_cpu_s": num_problems / max(best["cpu_seconds"], 1e-9),
        "mean_atoms": atoms,
        "target_problems_per_s": TARGET_PER_S,
        "meets_target": bool(per_s >= TARGET_PER_S),
    }


@register_bench("wnomp", "WNOMP throughput: (cell, grid) problems per second, M = 40 beams, N = 6552 bins")
def run(ctx: BenchContext) -> dict[str, Any]:
    num = 8192 if ctx.size == "quick" else 65536
    return run_wnomp_speed(num, device=ctx.device)
