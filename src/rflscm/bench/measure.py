"""Measurements beside the MAE that the benchmarks report: peak memory, rendering throughput, parameter
counts and APS recovery on arbitrary (cell, grid) pairs."""

from __future__ import annotations

import threading
import time
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
import torch

if TYPE_CHECKING:
    from rflscm.bench.harness import BenchData
    from rflscm.models.base import LSCMModel
    from rflscm.models.source import APSSource


# --- memory and throughput ----------------------------------------------------------------------------
def _rss_mb() -> float | None:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


class MemoryProbe:
    """Peak memory while the block runs: CUDA ``max_memory_allocated`` on a GPU, else the process RSS
    sampled every 20 ms from ``/proc/self/status`` (Linux; ``None`` elsewhere)."""

    def __init__(self, device: str) -> None:
        self.cuda = str(device).startswith("cuda")
        self.before: float | None = None
        self.peak: float | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> MemoryProbe:
        if self.cuda:
            torch.cuda.synchronize()
            torch.cuda.reset_peak_memory_stats()
            self.before = torch.cuda.memory_allocated() / 2**20
            return self
        self.before = self.peak = _rss_mb()
        if self.before is not None:
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        return self

    def _sample(self) -> None:
        while not self._stop.wait(0.02):
            rss = _rss_mb()
            if rss is not None and rss > (self.peak or 0.0):
                self.peak = rss

    def __exit__(self, *exc: object) -> None:
        if self.cuda:
            torch.cuda.synchronize()
            self.peak = torch.cuda.max_memory_allocated() / 2**20
            return
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        rss = _rss_mb()
        if rss is not None and self.peak is not None:
            self.peak = max(self.peak, rss)

    def result(self) -> dict[str, Any]:
        kind = "cuda_max_allocated" if self.cuda else "cpu_rss"
        inc = None if self.peak is None or self.before is None else max(self.peak - self.before, 0.0)
        return {"kind": kind, "peak_mb": self.peak, "increase_mb": inc}


def render_throughput(model: LSCMModel, data: BenchData, num_pairs: int = 64) -> dict[str, float | None]:
    """Inference throughput of a field model: ``model.aps`` on ``num_pairs`` training pairs.

    ``ray_samples_per_s`` counts every ray of the output (HiTAM: the coarse rays plus β²·K_C refinement
    rays per pair; without: every bin) times Q samples per ray, skipped empty samples included, so it
    compares like for like across models; ``decoder_evals_per_s`` counts the samples actually decoded.
    """
    from rflscm.models.rflscm import RFLSCM

    if not isinstance(model, RFLSCM) or model.scene is None:
        return {"pairs_per_s": None, "ray_samples_per_s": None, "decoder_evals_per_s": None}
    pairs = data.scenario.rsrp_table(1, "ssb")[0].iloc[:num_pairs]
    cells, grids = pairs["cell_id"].to_numpy(), pairs["grid_id"].to_numpy()
    xyz = data.scenario.grids.set_index("grid_id").loc[grids, ["x", "y", "z"]].to_numpy()
    evals0 = model.decoder_evals()
    if str(model.device).startswith("cuda"):
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    model.aps(cells, grids, xyz)
    if str(model.device).startswith("cuda"):
        torch.cuda.synchronize()
    dt = max(time.perf_counter() - t0, 1e-9)
    h = model.hitam
    rays = (h.num_coarse + h.num_fine_slots) if h is not None else model.angle_grid.num_bins
    q = model.scene.frame.num_samples
    return {
        "pairs_per_s": len(pairs) / dt,
        "ray_samples_per_s": len(pairs) * rays * q / dt,
        "decoder_evals_per_s": (model.decoder_evals() - evals0) / dt,
        "rays_per_pair": float(rays),
        "samples_per_ray": float(q),
    }


def aps_recovery(
    model: APSSource, oracle: APSSource | None, pairs: pd.DataFrame, top_k: int = 5, max_pairs: int = 500
) -> dict[str, Any]:
    """APS recovery of ``model`` against the true APS (``oracle``) on ``pairs`` (a seeded subsample of at
    most ``max_pairs``), in the form of :func:`rflscm.eval.run_evaluation`'s ``aps`` block (which it
    computes on test pairs only): the mean and median over pairs of the per-pair NMSE [dB]
    (:func:`~rflscm.eval.metrics.aps_nmse_db`) and the power-weighted angular error [deg] of the
    ``top_k`` strongest bins."""
    from rflscm.eval import metrics as M

    out: dict[str, Any] = {"nmse_db": None, "nmse_db_median": None, "angle_error_deg": None, "pairs": 0}
    if oracle is None or not len(pairs):
        return out
    if len(pairs) > max_pairs:
        pairs = pairs.iloc[np.sort(np.random.default_rng(0).choice(len(pairs), max_pairs, replace=False))]
    cells, grids = pairs["cell_id"].to_numpy(), pairs["grid_id"].to_numpy()
    with torch.no_grad():
        est = model.aps(cells, grids).detach().double().cpu().numpy()
        true = oracle.aps(cells, grids).detach().double().cpu().numpy()
    nmse_db = M.aps_nmse_db(est, true)
    finite = nmse_db[np.isfinite(nmse_db)]
    out["nmse_db"] = M.nanmean_or_none(nmse_db)
    out["nmse_db_median"] = float(np.median(finite)) if len(finite) else None
    out["angle_error_deg"] = M.nanmean_or_none(M.aps_angle_error_deg(est, true, model.angle_grid, top_k))
    out["pairs"] = int(len(pairs))
    return out


def parameter_count(model: object) -> int | None:
    stages = getattr(model, "stages", None)
    return None if stages is None else int(sum(p.numel() for p in stages.parameters()))
