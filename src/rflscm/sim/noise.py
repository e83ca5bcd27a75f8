"""The measurement model: from noiseless RSRP to reported RSRP (SPEC §2, §6).

A UE's report of beam m is r̂ = Q(r + n), n ~ N(0, σ²) in dB (log-normal in
linear units), Q rounding to the 1 dB report step; beams below the reporting
threshold r_th are not reported (NaN) and reported values are clipped to the
TS 38.133 reportable range −156…−31 dBm.  A (cell, grid) pair appears in the
data only when the UE detects the cell — by default when at least one of its SSB
beams is reported, since SSBs are how a UE finds cells; then all of its SSB and
CSI-RS beams are listed, missing ones as NaN.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from rflscm.data import RSRP_MAX_DBM, RSRP_MIN_DBM
from rflscm.errors import ConfigError


@dataclass(frozen=True)
class MeasurementModel:
    """Noise, quantisation and reporting threshold of simulated RSRP reports."""

    sigma_db: float = 2.0
    """Standard deviation of the log-normal measurement noise [dB]."""
    quantization_db: float = 1.0
    """Report step [dB] (0 = no quantisation)."""
    threshold_dbm: float = -120.0
    """Reporting threshold r_th [dBm]: quantised values below it are missing (NaN)."""

    def __post_init__(self) -> None:
        if self.sigma_db < 0 or self.quantization_db < 0:
            raise ConfigError(
                f"noise sigma and quantisation step must be >= 0 dB (got {self.sigma_db}, {self.quantization_db})."
            )
        if not RSRP_MIN_DBM <= self.threshold_dbm <= RSRP_MAX_DBM:
            raise ConfigError(
                f"reporting threshold {self.threshold_dbm} dBm is outside the reportable range −156…−31 dBm."
            )

    def apply(self, rsrp_dbm: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Reported RSRP [dBm] (same shape as ``rsrp_dbm``): noisy, quantised, NaN when not reported.

        ``rsrp_dbm`` may hold −inf (no path at all): never reported.
        """
        rsrp_dbm = np.asarray(rsrp_dbm, dtype=np.float64)
        noisy = rsrp_dbm + rng.normal(0.0, self.sigma_db, rsrp_dbm.shape) if self.sigma_db > 0 else rsrp_dbm.copy()
        if self.quantization_db > 0:
            noisy = np.round(noisy / self.quantization_db) * self.quantization_db
        reported = np.isfinite(noisy) & (noisy >= self.threshold_dbm)
        return np.where(reported, np.clip(noisy, RSRP_MIN_DBM, RSRP_MAX_DBM), np.nan)


def measure(
    noiseless: pd.DataFrame, model: MeasurementModel, rng: np.random.Generator, detect_on: str | None = "ssb"
) -> pd.DataFrame:
    """Measurements table from the long-form noiseless RSRP (``round``, ``cell_id``, ``grid_id``,
    ``beam_type``, ``beam_id``, ``rsrp_dbm``).

    Every row gets independent noise.  Only the rows of (round, cell, grid) pairs that the UE detects
    are kept: pairs with at least one reported beam of type ``detect_on`` (``"ssb"``: a UE finds cells
    by their SSB, and measures CSI-RS only on cells it found), or of any type with ``None``.
    """
    reported = model.apply(noiseless["rsrp_dbm"].to_numpy(), rng)
    table = noiseless.assign(rsrp_dbm=reported)
    heard = table["rsrp_dbm"].notna()
    if detect_on is not None:
        heard &= table["beam_type"] == detect_on
    detected = heard.groupby([table["round"], table["cell_id"], table["grid_id"]], sort=False).transform("any")
    return table[detected.to_numpy()].reset_index(drop=True)
