"""Training data of radiance-field LSCM models: (cell, grid) pairs with SSB and CSI-RS beams stacked.

Beam layout of every pair: columns ``0 … num_ssb−1`` are SSB beams, the rest CSI-RS beams; the
rows of the stacked sensing matrix follow the same layout (zero rows past a cell's codebook).
Everything is normalised (SPEC §3 numerical notes): r / r_ref with r_ref the median reported
RSRP [mW], A / a_ref with a_ref the median over cells of the largest entry of A, so x / x_ref
with x_ref = r_ref / a_ref is O(1) for a typical path seen by a beam peak.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch

from rflscm.data import BEAM_TYPES
from rflscm.data.reporting import missing_bounds
from rflscm.errors import DataError
from rflscm.geometry import AngleGrid

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario


@dataclass
class PairData:
    """Round-1 (cell, grid) samples of a scenario on one device."""

    cell_index: torch.Tensor  # long [P], index into the model's cells
    grid_ids: np.ndarray  # int64 [P]
    grid_xyz: torch.Tensor  # float32 [P, 3] [m]
    rsrp: torch.Tensor  # float32 [P, M], normalised linear, NaN = missing / absent
    beam_mask: torch.Tensor  # bool [P, M], beams used in training
    val_mask: torch.Tensor  # bool [P, M], beams held aside for validation
    x_scale: torch.Tensor  # float32 [P], least APS power explaining the strongest beam
    bound: torch.Tensor  # float32 [P, M], normalised linear upper bound of each missing beam under the
    #                      scenario's reporting rule (rflscm.data.reporting); NaN where reported or absent
    val_pairs: torch.Tensor  # long [V]

    @property
    def num_pairs(self) -> int:
        return int(self.cell_index.numel())

    @property
    def observed(self) -> torch.Tensor:
        """bool ``[P, M]``: the training beams that were reported (``beam_mask`` and a value)."""
        return self.beam_mask & ~torch.isnan(self.rsrp)

    def to(self, device: torch.device | str) -> PairData:
        """A copy with every tensor on ``device``."""
        moved = {k: (v.to(device) if isinstance(v, torch.Tensor) else v) for k, v in vars(self).items()}
        return PairData(**moved)  # type: ignore[arg-type]  # the same fields, tensors moved


def stacked_sensing(
    scenario: Scenario, cell_ids: np.ndarray, grid: AngleGrid, round: int = 1, device: torch.device | str = "cpu"
) -> tuple[torch.Tensor, int]:
    """A ``[num_cells, num_ssb + num_csi, num_bins]`` [mW] (float32) of both beam types, and num_ssb."""
    sizes = {t: max(scenario.num_beams(int(c), t, round) for c in cell_ids) for t in BEAM_TYPES}
    out = torch.zeros(len(cell_ids), sizes["ssb"] + sizes["csi"], grid.num_bins, device=device)
    for i, cell in enumerate(cell_ids):
        start = 0
        for t in BEAM_TYPES:
            a = scenario.sensing(int(cell), t, grid, round=round, dtype=torch.float32, device=device)
            out[i, start : start + a.shape[0]] = a
            start += sizes[t]
    return out, sizes["ssb"]


def build_pair_data(
    scenario: Scenario,
    cell_ids: np.ndarray,
    a_norm: torch.Tensor,
    num_ssb: int,
    r_ref_mw: float,
    val_pairs: int,
    val_fraction: float,
    seed: int,
) -> PairData:
    """Stack the round-1 SSB and CSI-RS tables of ``scenario`` into :class:`PairData`.

    ``a_norm [num_cells, M, N]`` is the normalised stacked sensing matrix (for ``x_scale``).  ``bound``
    holds each missing beam's upper bound under the scenario's reporting rule, per report
    (:func:`rflscm.data.reporting.missing_bounds`): r_th, the weakest reported beam of a full top-N
    report, or the SS-SINR detection level.
    """
    grid_all = scenario.grid_ids()
    keys, tables = [], {}
    for t in BEAM_TYPES:
        pairs, rsrp_dbm = scenario.rsrp_table(1, t)
        c = np.searchsorted(cell_ids, pairs["cell_id"].to_numpy())
        k = c * len(grid_all) + np.searchsorted(grid_all, pairs["grid_id"].to_numpy())
        tables[t] = (k, rsrp_dbm, missing_bounds(scenario, 1, t, pairs, rsrp_dbm))
        keys.append(k)
    union = np.unique(np.concatenate(keys))
    if union.size == 0:
        raise DataError(f"scenario {scenario.meta.name!r} has no round-1 measurements to train on.")
    num_beams = a_norm.shape[1]
    rsrp_dbm = np.full((union.size, num_beams), np.nan)
    bound_dbm = np.full((union.size, num_beams), np.nan)
    mask = np.zeros((union.size, num_beams), bool)
    cell_pos = union // len(grid_all)
    for t, offset in zip(BEAM_TYPES, (0, num_ssb)):
        k, table, bound_t = tables[t]
        rows = np.searchsorted(union, k)
        width = table.shape[1]
        rsrp_dbm[rows, offset : offset + width] = table
        bound_dbm[rows, offset : offset + width] = bound_t
        sizes = np.array([scenario.num_beams(int(c), t, 1) for c in cell_ids])[cell_pos[rows]]
        mask[rows, offset : offset + width] = np.arange(width)[None, :] < sizes[:, None]
    rsrp = 10.0 ** (rsrp_dbm / 10.0) / r_ref_mw
    val_mask = _hold_out(rsrp, mask, val_pairs, val_fraction, np.random.default_rng(seed))
    cell_index = torch.as_tensor(cell_pos, dtype=torch.long)
    peak = a_norm.flatten(1).max(1).values.cpu()[cell_index]  # [P]
    strongest = torch.as_tensor(np.nan_to_num(np.where(mask & ~val_mask, rsrp, np.nan), nan=0.0).max(1))
    threshold = 10.0 ** (scenario.meta.rsrp_threshold_dbm / 10.0) / r_ref_mw
    x_scale = torch.clamp(strongest.float(), min=threshold) / peak.clamp_min(1e-30)
    grid_ids = grid_all[union % len(grid_all)]
    xyz = scenario.grids.set_index("grid_id").loc[grid_ids, ["x", "y", "z"]].to_numpy(np.float32)
    return PairData(
        cell_index=cell_index,
        grid_ids=grid_ids,
        grid_xyz=torch.as_tensor(xyz),
        rsrp=torch.as_tensor(rsrp, dtype=torch.float32),
        beam_mask=torch.as_tensor(mask & ~val_mask),
        val_mask=torch.as_tensor(val_mask),
        x_scale=x_scale.float(),
        bound=torch.as_tensor(10.0 ** (bound_dbm / 10.0) / r_ref_mw, dtype=torch.float32),
        val_pairs=torch.as_tensor(np.flatnonzero(val_mask.any(1)), dtype=torch.long),
    )


def _hold_out(
    rsrp: np.ndarray, mask: np.ndarray, num_pairs: int, fraction: float, rng: np.random.Generator
) -> np.ndarray:
    """Validation mask: in up to ``num_pairs`` pairs with ≥ 2 reported beams, hide ``fraction`` of them
    (at least one, never all)."""
    val = np.zeros_like(mask)
    reported = mask & ~np.isnan(rsrp)
    candidates = np.flatnonzero(reported.sum(1) >= 2)
    if num_pairs <= 0 or fraction <= 0 or candidates.size == 0:
        return val
    chosen = rng.choice(candidates, size=min(num_pairs, candidates.size), replace=False)
    for p in np.sort(chosen):  # a few hundred pairs, once
        beams = np.flatnonzero(reported[p])
        count = min(max(1, int(round(fraction * beams.size))), beams.size - 1)
        val[p, rng.choice(beams, size=count, replace=False)] = True
    return val


def reference_power(rsrp: np.ndarray) -> float:
    """Median reported RSRP [mW] of a dBm array (NaN ignored)."""
    values = rsrp[~np.isnan(rsrp)]
    if values.size == 0:
        raise DataError("no reported RSRP in round 1: nothing to normalise or train on.")
    return float(10.0 ** (np.median(values) / 10.0))
