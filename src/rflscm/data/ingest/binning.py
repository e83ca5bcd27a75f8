"""Samples → grids and measurements: square bins, outlier rejection, linear-power means, minimum counts.

Grid (i, j) is the square [i·s, (i+1)·s) × [j·s, (j+1)·s) of the local frame (s = ``grid_size_m``); its
position is the square's centre at the mean height of its samples.  Per (round, cell, grid, beam type,
beam) bin:

1. *outliers*: with at least ``OUTLIER_MIN_SAMPLES`` (5) samples and a median absolute deviation (MAD) > 0, a sample more than
   ``outlier_k`` · 1.4826 · MAD from the bin's median [dB] is dropped (1.4826 · MAD estimates σ of
   Gaussian dB scatter, so k = 3 drops what a Gaussian would put beyond 3σ);
2. *minimum count*: a bin with fewer than ``min_samples`` samples left is dropped;
3. the value is the mean in linear power, 10 log10(mean(10^(r/10))) [dBm]; the bin's sample count and
   the standard deviation of its samples [dB] (0 for one sample) are kept beside it.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from rflscm.data.ingest.samples import Tally
from rflscm.data.ingest.spec import ImportSpec

OUTLIER_MIN_SAMPLES = 5
"""Fewer samples give no robust median and MAD (with 3, the farther of two deviations is often > 4.4 × the other)."""
BIN_KEY = ["round", "cell_id", "ix", "iy", "beam_type", "beam_id"]


def bin_samples(samples: pd.DataFrame, spec: ImportSpec, tally: Tally) -> pd.DataFrame:
    """One row per kept bin: ``BIN_KEY`` + ``rsrp_dbm`` (linear mean), ``samples``, ``std_db``, ``z`` (mean)."""
    s = spec.grid_size_m
    df = samples.assign(ix=np.floor(samples["x"] / s).astype(np.int64), iy=np.floor(samples["y"] / s).astype(np.int64))
    groups = df.groupby(BIN_KEY, sort=False)["rsrp_dbm"]
    if spec.outlier_k > 0:
        median = groups.transform("median")
        dev = (df["rsrp_dbm"] - median).abs()
        mad = dev.groupby([df[k] for k in BIN_KEY], sort=False).transform("median")
        count = groups.transform("size")
        outlier = ((count >= OUTLIER_MIN_SAMPLES) & (mad > 0) & (dev > spec.outlier_k * 1.4826 * mad)).to_numpy()
        tally.drop(f"outlier (> {spec.outlier_k:g}·1.4826·MAD from its bin's median)", int(outlier.sum()))
        df = df[~outlier]
    df = df.assign(mw=10.0 ** (df["rsrp_dbm"] / 10.0))
    agg = df.groupby(BIN_KEY, sort=True).agg(
        mw=("mw", "mean"), samples=("mw", "size"), std_db=("rsrp_dbm", "std"), z=("z", "sum")
    )
    agg = agg.reset_index()
    agg["std_db"] = agg["std_db"].fillna(0.0)
    few = agg["samples"].to_numpy() < spec.min_samples
    tally.drop(
        f"bin with fewer than min_samples = {spec.min_samples} samples", int(agg["samples"][few].sum()), int(few.sum())
    )
    agg = agg[~few].reset_index(drop=True)
    agg["rsrp_dbm"] = 10.0 * np.log10(agg.pop("mw"))
    return agg


def keep_top_n(bins: pd.DataFrame, beam_type: str, top_n: int, tally: Tally) -> pd.DataFrame:
    """Keep the ``top_n`` strongest beams of each (round, cell, grid) report of ``beam_type``; the rest counted.

    Each raw report carries at most N beams, but a bin gathers many reports, so it can hold more."""
    mine = (bins["beam_type"] == beam_type).to_numpy()
    rank = bins[mine].groupby(["round", "cell_id", "ix", "iy"])["rsrp_dbm"].rank(ascending=False, method="first")
    drop = np.zeros(len(bins), bool)
    drop[np.flatnonzero(mine)] = rank.to_numpy() > top_n
    tally.drop(
        f"{beam_type} bin beyond the top-{top_n} strongest of its grid (rule top_n)",
        int(bins["samples"][drop].sum()),
        int(drop.sum()),
    )
    return bins[~drop].reset_index(drop=True)


def grids_of(bins: pd.DataFrame, spec: ImportSpec) -> tuple[pd.DataFrame, np.ndarray]:
    """The grids table (``grid_id`` 0… in (ix, iy) order, centres, mean sample height) and each bin's grid id."""
    keys = pd.MultiIndex.from_arrays([bins["ix"].to_numpy(), bins["iy"].to_numpy()])
    codes, uniques = pd.factorize(keys, sort=True)
    zsum = np.bincount(codes, weights=bins["z"].to_numpy())
    n = np.bincount(codes, weights=bins["samples"].to_numpy())
    ix = np.array([u[0] for u in uniques], dtype=np.float64)
    iy = np.array([u[1] for u in uniques], dtype=np.float64)
    s = spec.grid_size_m
    grids = pd.DataFrame({"grid_id": np.arange(len(uniques)), "x": (ix + 0.5) * s, "y": (iy + 0.5) * s, "z": zsum / n})
    return grids, codes
