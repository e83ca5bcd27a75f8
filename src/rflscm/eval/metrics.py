"""Evaluation metrics (SPEC §5): RSRP MAE in dB, changed cells, the trivial baseline, APS recovery.

All functions are plain numpy on arrays aligned with a ``pairs`` table
(``cell_id``, ``grid_id``) and ``[num_pairs, max_beams]`` RSRP matrices [dBm]
where NaN marks a beam that was not reported (measured) or not predicted.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
import torch

from rflscm.geometry import AngleGrid

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario


# --- RSRP errors ------------------------------------------------------------------------------------
def abs_error_db(pred_dbm: np.ndarray, meas_dbm: np.ndarray) -> np.ndarray:
    """|pred − meas| [dB] ``[num_pairs, max_beams]``, NaN where either is NaN (beam not reported)."""
    return np.abs(np.asarray(pred_dbm, dtype=np.float64) - np.asarray(meas_dbm, dtype=np.float64))


def mae_db(err_db: np.ndarray, rows: np.ndarray | None = None) -> float | None:
    """Mean of the finite entries of ``err_db`` (rows selected by bool ``rows``); ``None`` when there are none.

    This is the paper's MAE (§V-B) averaged over reported (cell, grid, beam) triples.
    """
    err = err_db if rows is None else err_db[np.asarray(rows, dtype=bool)]
    finite = np.isfinite(err)
    return float(err[finite].mean()) if finite.any() else None


def count_finite(values: np.ndarray, rows: np.ndarray | None = None) -> int:
    """Number of finite entries (selected rows only)."""
    v = values if rows is None else values[np.asarray(rows, dtype=bool)]
    return int(np.isfinite(v).sum())


# --- changed cells -------------------------------------------------------------------------------------
def changed_cells(scenario: Scenario, round_a: int = 1, round_b: int = 2) -> np.ndarray:
    """Sorted ids of the cells whose antenna configuration differs between two rounds.

    A cell is *changed* when its antenna (azimuth, tilts, array, element, power) or its SSB or
    CSI-RS codebook differs; positions and carriers never change between rounds.
    """
    if round_a == round_b or round_b not in scenario.cells or round_a not in scenario.cells:
        return np.zeros(0, dtype=np.int64)
    changed = [
        int(c) for c in scenario.cell_ids() if _cell_config(scenario, c, round_a) != _cell_config(scenario, c, round_b)
    ]
    return np.asarray(changed, dtype=np.int64)


def _cell_config(scenario: Scenario, cell_id: int, round: int) -> tuple[str, ...]:
    # repr() of the frozen dataclasses: robust where a measured element pattern holds arrays.
    antenna = scenario.antenna(int(cell_id), round)
    fields = {f.name: getattr(antenna, f.name) for f in dataclasses.fields(antenna) if f.name != "element"}
    element = antenna.element
    return (
        repr(fields),
        repr(element) if dataclasses.is_dataclass(element) else f"{type(element).__name__}:{id(element)}",
        repr(scenario.codebook(int(cell_id), "ssb", round)),
        repr(scenario.codebook(int(cell_id), "csi", round)),
    )


# --- trivial baseline -------------------------------------------------------------------------------------
def trivial_prediction(train_scenario: Scenario, beam_type: str, pairs: pd.DataFrame, num_beams: int) -> np.ndarray:
    """The trivial baseline ``[num_pairs, num_beams]`` [dBm]: every beam of a pair gets the mean reported
    round-1 RSRP (in dB) of that pair and beam type in the training data; a pair absent from training gets
    its cell's mean, a cell absent from training the overall mean."""
    train_pairs, rsrp = train_scenario.rsrp_table(1, beam_type)
    reported = np.isfinite(rsrp)
    with np.errstate(all="ignore"):
        pair_mean = np.where(reported, rsrp, 0.0).sum(1) / reported.sum(1)  # NaN for a pair with none
    ok = np.isfinite(pair_mean)
    table = train_pairs.assign(mean=pair_mean)[ok]
    overall = float(table["mean"].mean()) if len(table) else np.nan
    cell_mean = table.groupby("cell_id")["mean"].mean()
    lookup = table.set_index(["cell_id", "grid_id"])["mean"]
    key = pd.MultiIndex.from_frame(pairs[["cell_id", "grid_id"]])
    value = lookup.reindex(key).to_numpy()
    fallback = cell_mean.reindex(pairs["cell_id"].to_numpy()).to_numpy()
    value = np.where(np.isfinite(value), value, np.where(np.isfinite(fallback), fallback, overall))
    return np.repeat(value[:, None], num_beams, axis=1)


# --- APS recovery --------------------------------------------------------------------------------------------
def aps_nmse(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Per-pair NMSE ‖x̂ − x‖² / ‖x‖² (linear) ``[num_pairs]``; NaN where the true APS is zero."""
    est = np.asarray(est, dtype=np.float64)
    true = np.asarray(true, dtype=np.float64)
    num = np.square(est - true).sum(1)
    den = np.square(true).sum(1)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(den > 0, num / den, np.nan)


def aps_nmse_db(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Per-pair NMSE in dB ``[num_pairs]`` (NaN where the true APS is zero; floored at −100 dB, an exact match).

    Averaging these dB values (a geometric mean of the linear NMSE) keeps a few wild estimates,
    which per-grid sparse recovery produces in badly conditioned directions, from swamping the mean.
    """
    nmse = aps_nmse(est, true)
    with np.errstate(divide="ignore", invalid="ignore"):
        return 10.0 * np.log10(np.maximum(nmse, 1e-10))


def aps_angle_error_deg(est: np.ndarray, true: np.ndarray, angle_grid: AngleGrid, top_k: int = 5) -> np.ndarray:
    """Power-weighted great-circle error [deg] ``[num_pairs]`` between the strongest bins of two APS.

    For each pair, the ``top_k`` strongest non-zero bins of the true APS and of the estimate are taken;
    each true bin is matched to its nearest estimated bin and vice versa, and the two directed mean
    distances (weighted by the power of the bin being matched) are averaged (a weighted Chamfer
    distance on the sphere).  NaN where either APS is all zero.
    """
    dirs = angle_grid.directions(dtype=torch.float64).numpy()  # [num_bins, 3]
    t_idx, t_w = _top_bins(true, top_k)
    e_idx, e_w = _top_bins(est, top_k)
    cos = np.einsum("pid,pjd->pij", dirs[t_idx], dirs[e_idx])  # [P, k, k]
    ang = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    big = np.where((t_w[:, :, None] > 0) & (e_w[:, None, :] > 0), ang, np.inf)
    with np.errstate(invalid="ignore", divide="ignore"):
        t_to_e = (np.where(t_w > 0, big.min(2), 0.0) * t_w).sum(1) / t_w.sum(1)
        e_to_t = (np.where(e_w > 0, big.min(1), 0.0) * e_w).sum(1) / e_w.sum(1)
    ok = (t_w.sum(1) > 0) & (e_w.sum(1) > 0)
    return np.where(ok, 0.5 * (t_to_e + e_to_t), np.nan)


def _top_bins(aps: np.ndarray, top_k: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices and powers ``[P, k]`` of the ``top_k`` strongest bins (power 0 where fewer are non-zero)."""
    aps = np.asarray(aps, dtype=np.float64)
    k = min(top_k, aps.shape[1])
    idx = np.argpartition(-aps, k - 1, axis=1)[:, :k]
    w = np.take_along_axis(aps, idx, axis=1)
    return idx, np.where(w > 0, w, 0.0)


def nanmean_or_none(values: np.ndarray) -> float | None:
    """Mean of the finite values, ``None`` when there are none."""
    values = np.asarray(values, dtype=np.float64)
    finite = np.isfinite(values)
    return float(values[finite].mean()) if finite.any() else None
