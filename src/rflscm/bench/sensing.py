"""Benchmark: the sensing matrix for 40 beams × 6552 bins × 32 elements (target < 50 ms on 2 CPU cores)."""

from __future__ import annotations

from typing import Any

import torch

from rflscm.antenna import CellAntenna, DFTCodebook, SSBCodebook, sensing_matrix, wavelength_of
from rflscm.bench import BenchContext, register_bench
from rflscm.bench.timing import time_call
from rflscm.geometry import AngleGrid


@register_bench("sensing", "sensing_matrix: 40 beams (8 SSB + 32 CSI-RS) × 6552 bins × 32 elements")
def run(ctx: BenchContext) -> dict[str, Any]:
    grid = AngleGrid()
    antenna = CellAntenna(azimuth_deg=120.0, mech_tilt_deg=4.0, elec_tilt_deg=2.0)
    wl = wavelength_of(3.5e9)
    results: dict[str, Any] = {"num_beams": 40, "num_bins": grid.num_bins, "num_elements": antenna.array.num_elements}
    for dtype in (torch.float32, torch.float64):

        def both(dtype: torch.dtype = dtype) -> None:
            sensing_matrix(antenna, SSBCodebook(), grid, wl, dtype=dtype, device=ctx.device)
            sensing_matrix(antenna, DFTCodebook(), grid, wl, dtype=dtype, device=ctx.device)

        results[str(dtype).removeprefix("torch.")] = time_call(
            both, repeats=30 if ctx.size == "quick" else 100, device=ctx.device
        )
    results["target_ms"] = 50.0
    results["meets_target"] = results["float32"]["median_ms"] < 50.0
    return results
