"""The simulator's ``truth/`` folder: writing it and reading the true APS.

``truth/`` holds (SPEC §6):

* ``paths.parquet`` — every traced path: ``site_id``, ``freq_hz``, ``grid_id``, ``point_id``,
  ``power_lin`` (isotropic path gain), ``aod_el_rad``, ``aod_az_rad``, ``delay_s``, ``interactions``;
* ``aps.parquet`` — the true APS, sparse long form: ``cell_id``, ``grid_id``, ``bin`` (flat index on
  the angle grid of ``scenario.yaml``'s ``simulation.angle_grid``), ``power_lin`` (nonzero bins only);
* ``rsrp_noiseless.parquet`` — ``round``, ``cell_id``, ``grid_id``, ``beam_type``, ``beam_id``,
  ``rsrp_dbm`` before noise, quantisation and threshold, rounded to 0.01 dB (−inf: no path); pairs
  whose strongest beam lies more than ``truth_rsrp_margin_db`` (10 dB) below the reporting
  threshold are left out, as they can never be reported.

Models never read ``truth/``; only evaluation does, through :class:`rflscm.eval.oracle.OracleModel`
(the evaluation floor), which answers with the true APS.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
import torch

from rflscm.data.io import read_table
from rflscm.errors import DataError, UnsupportedError
from rflscm.geometry import AngleGrid
from rflscm.sim.paths import APS_FILE, PATHS_FILE, RSRP_FILE, true_aps_table, write_truth  # noqa: F401

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario


class TrueAPS:
    """The true APS of (cell, grid) pairs, dense on request.

    Args:
        table: ``cell_id``, ``grid_id``, ``bin``, ``power_lin`` (nonzero bins).
        angle_grid: the grid the bins index.
        cell_ids, grid_ids: the cells and grids the truth covers; a covered pair with no rows
            has a zero APS (no path reached the grid).
    """

    def __init__(self, table: pd.DataFrame, angle_grid: AngleGrid, cell_ids: np.ndarray, grid_ids: np.ndarray) -> None:
        self.angle_grid = angle_grid
        self.cell_ids = np.unique(np.asarray(cell_ids, dtype=np.int64))
        self.grid_ids = np.unique(np.asarray(grid_ids, dtype=np.int64))
        # Match rows to the covered cells and grids by id, and drop the rest: truth/ covers the whole
        # simulated scenario, a scenario restricted to some cells or grids only a part of it (a row
        # of an uncovered id must not land on the position of its covered neighbour).
        c, c_known = _index_of(self.cell_ids, table["cell_id"].to_numpy(np.int64))
        g, g_known = _index_of(self.grid_ids, table["grid_id"].to_numpy(np.int64))
        known = c_known & g_known
        key = c[known] * len(self.grid_ids) + g[known]
        order = np.argsort(key, kind="stable")
        self._keys, self._start, self._count = np.unique(key[order], return_index=True, return_counts=True)
        self._bins = table["bin"].to_numpy(np.int64)[known][order]
        self._power = table["power_lin"].to_numpy(np.float64)[known][order]
        if len(self._bins) and self._bins.max() >= angle_grid.num_bins:
            raise DataError(
                f"true APS bin {int(self._bins.max())} is outside the {angle_grid.num_bins}-bin angle grid."
            )

    def _positions(self, ids: np.ndarray, known: np.ndarray, what: str) -> np.ndarray:
        pos, found = _index_of(known, ids)
        if not found.all():
            missing = ", ".join(str(v) for v in np.unique(ids[~found])[:5])
            raise UnsupportedError(f"no true APS for {what} {missing} (the simulation did not trace it).")
        return pos

    def aps(
        self,
        cell_ids: np.ndarray,
        grid_ids: np.ndarray,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """Dense APS ``[num_pairs, num_bins]`` (linear path gain) of pairs ``cell_ids[i]``, ``grid_ids[i]``."""
        cell_ids = np.asarray(cell_ids, dtype=np.int64).reshape(-1)
        grid_ids = np.asarray(grid_ids, dtype=np.int64).reshape(-1)
        key = self._positions(cell_ids, self.cell_ids, "cell") * len(self.grid_ids)
        key = key + self._positions(grid_ids, self.grid_ids, "grid")
        out = np.zeros((len(key), self.angle_grid.num_bins), dtype=np.float32 if dtype == torch.float32 else np.float64)
        idx = np.clip(np.searchsorted(self._keys, key), 0, max(len(self._keys) - 1, 0))
        has = (self._keys[idx] == key) if len(self._keys) else np.zeros(len(key), dtype=bool)
        counts = np.where(has, self._count[idx] if len(self._keys) else 0, 0)
        pair = np.repeat(np.arange(len(key)), counts)
        rows = np.repeat(self._start[idx] if len(self._keys) else np.zeros(len(key), int), counts)
        rows += np.arange(len(rows)) - np.repeat(np.cumsum(counts) - counts, counts)
        out[pair, self._bins[rows]] = self._power[rows]
        return torch.as_tensor(out, dtype=dtype, device=device)


def _index_of(known: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions of ``ids`` in the sorted unique array ``known`` and whether each id is there at all
    (the position of a missing id is meaningless)."""
    if len(known) == 0:
        return np.zeros(len(ids), dtype=np.int64), np.zeros(len(ids), dtype=bool)
    pos = np.minimum(np.searchsorted(known, ids), len(known) - 1).astype(np.int64)
    return pos, known[pos] == ids


def truth_folder(scenario: Scenario) -> Path:
    """The scenario's ``truth/`` folder, or a :class:`DataError` saying that it has none."""
    if scenario.meta.truth is None or not (scenario.root / scenario.meta.truth).is_dir():
        raise DataError(
            f"scenario {scenario.meta.name!r} ({scenario.root}) has no truth folder; only scenarios made by "
            "`rflscm simulate` carry ground truth."
        )
    return scenario.root / scenario.meta.truth


def simulation_angle_grid(simulation: dict[str, Any]) -> AngleGrid:
    """The angle grid ``truth/aps.parquet`` is binned on (``scenario.yaml`` ``simulation.angle_grid``)."""
    spec = simulation.get("angle_grid")
    if not isinstance(spec, dict):
        raise DataError("scenario.yaml `simulation.angle_grid` is missing; the truth folder cannot be read.")
    return AngleGrid.from_dict(spec)


SAMPLES_APS_FILE = "aps_samples.parquet"
"""Field regime: the true APS of each round's UE samples (``round`` + the columns of ``aps.parquet``)."""


def load_true_aps(scenario: Scenario, angle_grid: AngleGrid | None = None, sample_round: int | None = None) -> TrueAPS:
    """The true APS of ``scenario`` (from ``truth/``), on its simulation grid or re-binned onto ``angle_grid``.

    ``sample_round``: the APS of that round's UE samples (``truth/aps_samples.parquet``, field regime) when
    the folder has it and no re-binning is needed; otherwise the APS over all traced points.
    """
    simulation = scenario.meta.simulation
    native = simulation_angle_grid(simulation)
    per_round = truth_folder(scenario) / SAMPLES_APS_FILE
    if sample_round is not None and per_round.is_file() and (angle_grid is None or angle_grid == native):
        table = read_table(per_round)
        table = table[(table["round"] == sample_round).to_numpy()].drop(columns="round")
        return TrueAPS(table, native, scenario.cells[1]["cell_id"].to_numpy(), scenario.grid_ids())
    return read_true_aps(
        truth_folder(scenario),
        scenario.cells[1],
        scenario.grid_ids(),
        simulation_angle_grid(simulation),
        simulation.get("points_per_grid"),
        angle_grid,
    )


def read_true_aps(
    folder: Path,
    cells: pd.DataFrame,
    grid_ids: np.ndarray,
    native: AngleGrid,
    points_per_grid: int | None,
    angle_grid: AngleGrid | None = None,
) -> TrueAPS:
    """Read ``folder/aps.parquet`` (binned on ``native``), or re-bin ``folder/paths.parquet`` onto
    another ``angle_grid`` (needs the cells' ``site_id``/``freq_hz`` and the points per grid)."""
    if angle_grid is None or angle_grid == native:
        return TrueAPS(read_table(folder / APS_FILE), native, cells["cell_id"].to_numpy(), grid_ids)
    if points_per_grid is None:
        raise DataError("scenario.yaml `simulation.points_per_grid` is missing; the APS cannot be re-binned.")
    paths = read_table(folder / PATHS_FILE)
    paths = paths.astype({"power_lin": "float64", "aod_el_rad": "float64", "aod_az_rad": "float64"})
    table = true_aps_table(paths, cells, angle_grid, int(points_per_grid))
    return TrueAPS(table, angle_grid, cells["cell_id"].to_numpy(), grid_ids)
