"""True KPIs of a configuration from the ray-traced paths in ``truth/`` (issue 13, deliverable 5).

The true best-beam SSB RSRP of every (cell, grid) under any cells table uses the simulator's own
formula, :func:`rflscm.sim.paths.path_rsrp_mw`: r_m = (1/K) Σ_{paths} P_t G_elem(ω_p) |w_mᴴ a(ω_p)|² |a_p|²
on the paths' own directions (no binning).  It is the **noiseless expectation**: measurement noise,
quantisation and the reporting rule change what a UE reports, not the coverage a configuration
gives, so the KPI truth leaves them out.  The shipped scenario is in the ideal regime (no array
errors); a field-regime scenario's extra effects are not modelled here (reported as such).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from rflscm.errors import DataError
from rflscm.network.kpi import KPIConfig, network_kpis
from rflscm.network.space import VARIABLES

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario


class TruthVerifier:
    """Computes true best-beam powers from ``truth/paths.parquet``, caching each cell's settings.

    Raises:
        DataError: the scenario has no ``truth/`` folder (verification asked of a measured scenario).
    """

    def __init__(self, scenario: Scenario) -> None:
        from rflscm.data.io import read_table
        from rflscm.sim.paths import PATHS_FILE, site_groups
        from rflscm.sim.truth import truth_folder

        folder = truth_folder(scenario)
        ppg = scenario.meta.simulation.get("points_per_grid")
        if ppg is None:
            raise DataError("scenario.yaml `simulation.points_per_grid` is missing; the true RSRP cannot be computed.")
        paths = read_table(folder / PATHS_FILE).astype(
            {"power_lin": "float64", "aod_el_rad": "float64", "aod_az_rad": "float64"}
        )
        self.scenario = scenario
        self.points_per_grid = int(ppg)
        self.groups = site_groups(paths)
        self.empty = paths.iloc[:0]
        self.regime = str(scenario.meta.simulation.get("regime", "ideal"))
        self._cache: dict[tuple[Any, ...], np.ndarray] = {}

    def best_power(self, cells: pd.DataFrame) -> np.ndarray:
        """True best-beam SSB RSRP ``[num_cells, num_grids]`` [mW] of the cells table ``cells``."""
        from rflscm.sim.paths import path_rsrp_mw

        scen = dataclasses.replace(
            self.scenario,
            cells={**self.scenario.cells, 0: cells.reset_index(drop=True)},
        )
        scen._elements.update(self.scenario._elements)
        grid_ids = scen.grid_ids()
        out = np.zeros((len(cells), len(grid_ids)))
        for i, cell_id in enumerate(scen.cell_ids()):
            row = scen.cell_row(int(cell_id), 0)
            key = (int(cell_id), *(row[v] for v in VARIABLES))
            if key not in self._cache:
                sub = self.groups.get((int(row["site_id"]), float(row["freq_hz"])), self.empty)
                rsrp = path_rsrp_mw(
                    sub,
                    scen.antenna(int(cell_id), 0),
                    scen.codebook(int(cell_id), "ssb", 0),
                    scen.wavelength_m(int(cell_id)),
                    grid_ids,
                    self.points_per_grid,
                )
                self._cache[key] = rsrp.max(axis=1) if rsrp.shape[1] else np.zeros(len(grid_ids))
            out[i] = self._cache[key]
        return out

    def kpis(self, cells: pd.DataFrame, kpi: KPIConfig, known: np.ndarray | None = None) -> dict[str, Any]:
        """True network KPIs of ``cells`` (on the pairs ``known`` when given, e.g. WNOMP's)."""
        freqs = cells.sort_values("cell_id")["freq_hz"].to_numpy()
        return network_kpis(self.best_power(cells.sort_values("cell_id")), freqs, kpi, known)
