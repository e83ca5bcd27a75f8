"""The KPI layers of one round: predicted RSRP of every pair through the prediction path of ``rflscm
predict`` (:class:`~rflscm.eval.cache.APSCache`, :func:`~rflscm.models.source.predict_rsrp`), then best
server, serving cell, SS-SINR and coverage per carrier from :mod:`rflscm.network.kpi`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from rflscm.eval.cache import APSCache
from rflscm.network.kpi import SIGNAL_FLOOR_MW, KPIConfig, best_beam_power_from_rsrp, carrier_groups, grid_maps

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.models.source import APSSource


@dataclass
class CarrierLayer:
    """KPIs of one carrier in one round; ``[num_grids]`` arrays in the scenario's grid order, NaN (−1 for
    ``serving``) where no cell of the carrier has a predicted pair at the grid."""

    freq_hz: float
    cell_ids: np.ndarray
    """The carrier's cells ``[num_carrier_cells]``, sorted."""
    rsrp_dbm: np.ndarray
    """Best-server SSB RSRP [dBm]."""
    serving: np.ndarray
    """Serving cell id (int64, −1: none)."""
    sinr_db: np.ndarray
    """SS-SINR [dB] of the serving cell."""
    covered: np.ndarray
    """1.0 where best-server RSRP ≥ the threshold, 0.0 below, NaN without a prediction."""
    cell_rsrp_dbm: np.ndarray
    """Best-beam SSB RSRP [dBm] of each of the carrier's cells ``[num_carrier_cells, num_grids]`` (NaN: no pair)."""
    cell_sinr_db: np.ndarray
    """SS-SINR [dB] each cell would have as the server (the others interfering), same shape (NaN: no pair)."""

    @property
    def label(self) -> str:
        return f"{self.freq_hz / 1e9:g} GHz"

    @property
    def key(self) -> str:
        return f"{self.freq_hz / 1e9:g}GHz"


@dataclass
class RoundLayers:
    """The KPI layers of one round of a scenario under one model."""

    round: int
    carriers: list[CarrierLayer]
    pairs: str
    """Which pairs were predicted: every (cell, grid) pair, or the measured round-1 pairs (WNOMP)."""
    threshold_dbm: float


def map_pairs(scenario: Scenario, source: APSSource) -> pd.DataFrame:
    """The (cell, grid) pairs a map predicts: every pair, or, for a model without unseen grids (WNOMP), the
    measured round-1 pairs, the pairs of ``rflscm predict --pairs measured``."""
    if source.supports_unseen_grids:
        cells, grids = np.meshgrid(scenario.cell_ids(), scenario.grid_ids(), indexing="ij")
        return pd.DataFrame({"cell_id": cells.ravel(), "grid_id": grids.ravel()})
    m = scenario.measurements
    m = m[(m["round"] == 1).to_numpy()]
    return m[["cell_id", "grid_id"]].drop_duplicates().sort_values(["cell_id", "grid_id"]).reset_index(drop=True)


def round_layers(source: APSSource, scenario: Scenario, round: int, cfg: KPIConfig | None = None) -> RoundLayers:
    """KPI layers of ``round``'s antenna configuration.  Pass an :class:`APSCache` to share APS across rounds."""
    cfg = cfg or KPIConfig()
    cache = APSCache.of(source)
    pairs = map_pairs(scenario, cache)
    rsrp = cache.predict_rsrp(scenario, round, "ssb", pairs)  # [pairs, beams] dBm, as `rflscm predict`
    cell_ids, grid_ids = scenario.cell_ids(), scenario.grid_ids()
    power, known = best_beam_power_from_rsrp(
        rsrp, pairs["cell_id"].to_numpy(), pairs["grid_id"].to_numpy(), cell_ids, grid_ids
    )
    freqs = np.array([float(f) for f in scenario.cells[round]["freq_hz"]])
    all_known = bool(known.all())
    maps = grid_maps(power, cell_ids, freqs, cfg, None if all_known else known)
    carriers = []
    for (freq, rows), m in zip(carrier_groups(freqs), maps, strict=True):
        p = np.where(power[rows] >= SIGNAL_FLOOR_MW, power[rows], 0.0) * known[rows]
        noise_mw = 10.0 ** (cfg.noise_per_re_dbm(freq) / 10.0)
        with np.errstate(divide="ignore"):
            cell_sinr = 10.0 * np.log10(np.maximum(p / (p.sum(axis=0) - p + noise_mw), 1e-30))
            cell_rsrp = 10.0 * np.log10(np.maximum(power[rows], 1e-30))
        nan = ~m.valid
        carriers.append(
            CarrierLayer(
                freq_hz=freq,
                cell_ids=cell_ids[rows],
                rsrp_dbm=np.where(nan, np.nan, m.best_rsrp_dbm),
                serving=np.asarray(m.serving_cell, np.int64),
                sinr_db=np.where(nan, np.nan, m.sinr_db),
                covered=np.where(nan, np.nan, (m.best_rsrp_dbm >= cfg.threshold_dbm).astype(np.float64)),
                cell_rsrp_dbm=np.where(known[rows], cell_rsrp, np.nan),
                cell_sinr_db=np.where(known[rows], cell_sinr, np.nan),
            )
        )
    which = "every (cell, grid) pair" if all_known else f"the {int(known.sum())} measured round-1 (cell, grid) pairs"
    return RoundLayers(round, carriers, which, cfg.threshold_dbm)
