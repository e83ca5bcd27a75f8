"""Network KPIs from best-beam SSB RSRP: best server, SS-SINR, coverage, overlap (issue 13).

Everything starts from one matrix: the **best-beam SSB RSRP** of every cell at every grid,
``power_mw[..., num_cells, num_grids]`` [mW per resource element], i.e. max over the cell's SSB
beams of r = A x.  A zero means "no signal" (or, for WNOMP, "no APS for this pair").  Leading
dimensions batch candidate configurations.  Per grid and carrier:

* **best-server RSRP** = max over the carrier's cells; **serving cell** = its arg max;
* **SS-SINR** = S / (Σ_{other cells on the carrier} P + N_RE), all per resource element
  (TS 38.215 §5.1.5 defines SS-SINR per RE carrying the SSS).  Interference is every other cell's
  best-beam power at full SSB collision (synchronised SSB bursts: the worst case, what planners
  assume for SSB); N_RE = −174 dBm/Hz + 10 log10(SCS) + NF.  Over the SSB's 20 PRB × 12
  subcarriers the noise is 10 log10(240) = 23.8 dB higher, and so is the signal: the ratio is the
  same.  At 30 kHz SCS and NF 7 dB, N_RE = −122.2 dBm; at 15 kHz, −125.2 dBm;
* **coverage**: best-server RSRP ≥ ``threshold_dbm`` (default −105 dBm);
* **overlap**: at least ``overlap_servers`` cells (the server included) within ``overlap_db`` of
  the best server (default 3 within 6 dB, the usual "pilot pollution" rule).

Area KPIs pool every (grid, carrier) sample that has at least one known pair.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from rflscm.errors import ConfigError

THERMAL_NOISE_DBM_PER_HZ = -174.0
"""kT at 290 K [dBm/Hz]."""
SSB_SUBCARRIERS = 20 * 12
"""An SS/PBCH block spans 20 PRB × 12 subcarriers (TS 38.211 §7.4.3.1)."""
MIN_POWER_MW = 1e-30
SIGNAL_FLOOR_MW = 1e-20
"""Powers below −200 dBm are "no signal" (0): prediction code floors a zero power at 1e-30 mW before dB."""
SINR_FLOOR_DB = -30.0
"""SINR statistics floor a grid's SINR here [dB]: a grid with no signal at all (no traced path) would
otherwise put −∞ into the mean; −30 dB is far below SSB detection (≈ −6 dB), so nothing is flattered."""
RSRP_FLOOR_DBM = -156.0
"""Mean RSRP floors a grid's best-server RSRP here [dBm] (the low end of the reportable range,
TS 38.133 SS-RSRP mapping), so that a grid without signal does not put −300 dBm into the mean."""
SINR_CLIP_DB = (-20.0, 30.0)
"""SINR range the ``sinr``/``weighted`` objectives average over: above 30 dB link adaptation buys nothing."""


@dataclass(frozen=True)
class KPIConfig:
    """Constants of the network KPIs (all documented in docs/DECISIONS.md, "Optimisation")."""

    threshold_dbm: float = -105.0
    """Coverage threshold on best-server SSB RSRP [dBm]."""
    noise_figure_db: float = 7.0
    """UE noise figure [dB] (3GPP TR 38.901/TR 38.802 evaluations use 7–9 dB)."""
    scs_hz: dict[float, float] = field(default_factory=dict)
    """SSB subcarrier spacing [Hz] per carrier [Hz]; a carrier not listed gets :func:`default_scs_hz`."""
    overlap_db: float = 6.0
    overlap_servers: int = 3
    """A grid overlaps when at least this many cells (server included) are within ``overlap_db``."""

    def __post_init__(self) -> None:
        if self.overlap_servers < 2:
            raise ConfigError(f"`overlap_servers` must be >= 2 (got {self.overlap_servers}).")
        if self.overlap_db <= 0:
            raise ConfigError(f"`overlap_db` must be > 0 dB (got {self.overlap_db}).")
        if not 0.0 <= self.noise_figure_db <= 30.0:
            raise ConfigError(f"`noise_figure_db` must lie in 0…30 dB (got {self.noise_figure_db}).")

    def noise_per_re_dbm(self, freq_hz: float) -> float:
        """Thermal noise per SSB resource element [dBm]: −174 + 10 log10(SCS) + NF."""
        scs = self.scs_hz.get(float(freq_hz), default_scs_hz(freq_hz))
        return THERMAL_NOISE_DBM_PER_HZ + 10.0 * math.log10(scs) + self.noise_figure_db

    def describe(self, freqs_hz: list[float]) -> dict[str, Any]:
        """Plain-data constants for reports: threshold, NF and per-carrier SCS / noise figures."""
        carriers = {}
        for f in sorted({float(v) for v in freqs_hz}):
            noise_re = self.noise_per_re_dbm(f)
            carriers[f"{f / 1e9:g} GHz"] = {
                "scs_khz": self.scs_hz.get(f, default_scs_hz(f)) / 1e3,
                "noise_per_re_dbm": round(noise_re, 2),
                "noise_ssb_bw_dbm": round(noise_re + 10.0 * math.log10(SSB_SUBCARRIERS), 2),
            }
        return {
            "threshold_dbm": self.threshold_dbm,
            "noise_figure_db": self.noise_figure_db,
            "overlap": f">= {self.overlap_servers} cells within {self.overlap_db:g} dB",
            "carriers": carriers,
        }


def default_scs_hz(freq_hz: float) -> float:
    """SSB subcarrier spacing of FR1 defaults: 30 kHz at and above 3 GHz (n77/n78, TS 38.101-1 Table
    5.4.3.3-1), 15 kHz below (e.g. n1 at 2.1 GHz)."""
    return 30e3 if float(freq_hz) >= 3e9 else 15e3


@dataclass
class GridMaps:
    """Per (carrier, grid) maps of one configuration, for reports (numpy, ``[num_grids]`` each)."""

    freq_hz: float
    best_rsrp_dbm: np.ndarray
    serving_cell: np.ndarray
    """Serving cell id (−1 where the grid has no known pair)."""
    sinr_db: np.ndarray
    valid: np.ndarray


def carrier_groups(cell_freq_hz: np.ndarray) -> list[tuple[float, np.ndarray]]:
    """``[(freq_hz, cell positions)]`` in ascending carrier order."""
    freqs = np.asarray(cell_freq_hz, dtype=np.float64)
    return [(float(f), np.flatnonzero(freqs == f)) for f in np.unique(freqs)]


def carrier_samples(
    power_mw: torch.Tensor, noise_mw: float, known: torch.Tensor | None, cfg: KPIConfig
) -> dict[str, torch.Tensor]:
    """Per-grid quantities of one carrier.

    Args:
        power_mw: best-beam RSRP ``[..., num_cells, num_grids]`` [mW] of the carrier's cells.
        noise_mw: thermal noise per RE [mW].
        known: ``[num_cells, num_grids]`` pairs with an APS, or None (all known).
        cfg: KPI constants.

    Returns:
        ``best_mw``, ``sinr_lin``, ``overlap`` (bool), ``server`` (cell position) ``[..., num_grids]``
        and ``valid`` ``[num_grids]`` (grids with at least one known pair).
    """
    power_mw = torch.where(power_mw >= SIGNAL_FLOOR_MW, power_mw, torch.zeros_like(power_mw))
    if known is not None:
        power_mw = power_mw * known.to(power_mw.dtype)
    best_mw, server = power_mw.max(dim=-2)
    total = power_mw.sum(dim=-2)
    sinr = best_mw / ((total - best_mw).clamp_min(0.0) + noise_mw)
    near = power_mw >= best_mw.unsqueeze(-2) * 10.0 ** (-cfg.overlap_db / 10.0)
    overlap = (near & (power_mw > 0)).sum(dim=-2) >= cfg.overlap_servers
    num_grids = power_mw.shape[-1]
    valid = known.any(dim=0) if known is not None else torch.ones(num_grids, dtype=torch.bool, device=power_mw.device)
    return {
        "best_mw": best_mw,
        "sinr_lin": sinr,
        "overlap": overlap,
        "server": server,
        "valid": valid,
    }


def area_kpis(
    samples: list[dict[str, torch.Tensor]], cfg: KPIConfig, percentile: bool = True
) -> dict[str, torch.Tensor]:
    """Area KPIs pooled over every valid (grid, carrier) sample of ``samples`` (one dict per carrier,
    from :func:`carrier_samples`, same leading dimensions).

    Returns tensors ``[...]``: ``coverage`` (fraction with RSRP ≥ threshold), ``mean_sinr_db``,
    ``p5_sinr_db`` (5th percentile; both with each grid's SINR floored at :data:`SINR_FLOOR_DB`),
    ``overlap`` (fraction), ``mean_rsrp_dbm`` (floored at :data:`RSRP_FLOOR_DBM`), ``no_signal``
    (fraction of samples that no cell reaches), ``margin``
    (mean of (RSRP − threshold)/10 dB clipped to ±1, the coverage objective's tie-break),
    ``mean_sinr_clipped_db`` (mean of SINR clipped to :data:`SINR_CLIP_DB`), ``num_samples``.
    """
    best = torch.cat([s["best_mw"][..., s["valid"]] for s in samples], dim=-1)
    sinr = torch.cat([s["sinr_lin"][..., s["valid"]] for s in samples], dim=-1)
    overlap = torch.cat([s["overlap"][..., s["valid"]] for s in samples], dim=-1)
    n = best.shape[-1]
    if n == 0:
        raise ConfigError("no (grid, carrier) sample has a known pair; the network KPIs are undefined.")
    rsrp_dbm, sinr_db = _sample_db(best, sinr)
    terms = objective_terms(rsrp_dbm, sinr_db, cfg)
    return {
        "coverage": terms["coverage"].mean(dim=-1),
        "mean_sinr_db": sinr_db.mean(dim=-1),
        "p5_sinr_db": torch.quantile(sinr_db, 0.05, dim=-1) if percentile else torch.full_like(best[..., 0], torch.nan),
        "overlap": overlap.to(best.dtype).mean(dim=-1),
        "mean_rsrp_dbm": rsrp_dbm.clamp_min(RSRP_FLOOR_DBM).mean(dim=-1),
        "no_signal": (best <= 0).to(best.dtype).mean(dim=-1),
        "margin": terms["margin"].mean(dim=-1),
        "mean_sinr_clipped_db": terms["mean_sinr_clipped_db"].mean(dim=-1),
        "num_samples": torch.full_like(best[..., 0], float(n)),
    }


def _sample_db(best: torch.Tensor, sinr: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-sample best-server RSRP [dBm] and SINR [dB] (floored at :data:`SINR_FLOOR_DB`)."""
    rsrp_dbm = 10.0 * torch.log10(best.clamp_min(MIN_POWER_MW))
    sinr_db = (10.0 * torch.log10(sinr.clamp_min(MIN_POWER_MW))).clamp_min(SINR_FLOOR_DB)
    return rsrp_dbm, sinr_db


def objective_terms(rsrp_dbm: torch.Tensor, sinr_db: torch.Tensor, cfg: KPIConfig) -> dict[str, torch.Tensor]:
    """Per-sample terms whose means are the objectives' KPIs: ``coverage`` (1 where RSRP ≥ threshold),
    ``margin`` ((RSRP − threshold)/10 dB clipped to ±1) and ``mean_sinr_clipped_db`` (SINR clipped to
    :data:`SINR_CLIP_DB`), each ``[..., num_samples]``."""
    lo, hi = SINR_CLIP_DB
    return {
        "coverage": (rsrp_dbm >= cfg.threshold_dbm).to(rsrp_dbm.dtype),
        "margin": ((rsrp_dbm - cfg.threshold_dbm) / 10.0).clamp(-1.0, 1.0),
        "mean_sinr_clipped_db": sinr_db.clamp(lo, hi),
    }


def objective_sums(samples: list[dict[str, torch.Tensor]], cfg: KPIConfig) -> dict[str, torch.Tensor]:
    """Sums ``[...]`` (float64) over the valid samples of ``samples`` (as :func:`area_kpis` takes them) of the
    :func:`objective_terms`: what a change confined to some grids moves the objectives' KPIs by, × samples."""
    out: dict[str, torch.Tensor] = {}
    for s in samples:
        rsrp_dbm, sinr_db = _sample_db(s["best_mw"][..., s["valid"]], s["sinr_lin"][..., s["valid"]])
        for key, term in objective_terms(rsrp_dbm, sinr_db, cfg).items():
            total = term.double().sum(dim=-1)
            out[key] = out[key] + total if key in out else total
    return out


def network_kpis(
    power_mw: torch.Tensor | np.ndarray,
    cell_freq_hz: np.ndarray,
    cfg: KPIConfig | None = None,
    known: torch.Tensor | np.ndarray | None = None,
) -> dict[str, Any]:
    """Area KPIs of one configuration, pooled and per carrier (plain floats, for JSON and reports).

    Args:
        power_mw: best-beam SSB RSRP ``[num_cells, num_grids]`` [mW].
        cell_freq_hz: carrier of each row ``[num_cells]`` [Hz].
        cfg: KPI constants (defaults: −105 dBm, NF 7 dB, 3 cells within 6 dB).
        known: ``[num_cells, num_grids]`` pairs the model has an APS for (WNOMP), or None.
    """
    cfg = cfg or KPIConfig()
    power = torch.as_tensor(np.asarray(power_mw), dtype=torch.float64)
    known_t = None if known is None else torch.as_tensor(np.asarray(known), dtype=torch.bool)
    per_carrier, samples = {}, []
    for freq, rows in carrier_groups(cell_freq_hz):
        idx = torch.as_tensor(rows)
        noise = 10.0 ** (cfg.noise_per_re_dbm(freq) / 10.0)
        s = carrier_samples(power[idx], noise, None if known_t is None else known_t[idx], cfg)
        samples.append(s)
        per_carrier[f"{freq / 1e9:g} GHz"] = _floats(area_kpis([s], cfg))
    out: dict[str, Any] = dict(_floats(area_kpis(samples, cfg)))
    out["per_carrier"] = per_carrier
    return out


def grid_maps(
    power_mw: np.ndarray,
    cell_ids: np.ndarray,
    cell_freq_hz: np.ndarray,
    cfg: KPIConfig | None = None,
    known: np.ndarray | None = None,
) -> list[GridMaps]:
    """Per-carrier maps (best-server RSRP, serving cell id, SINR) of one configuration ``[num_cells, num_grids]``."""
    cfg = cfg or KPIConfig()
    power = torch.as_tensor(np.asarray(power_mw), dtype=torch.float64)
    maps = []
    for freq, rows in carrier_groups(cell_freq_hz):
        noise = 10.0 ** (cfg.noise_per_re_dbm(freq) / 10.0)
        k = None if known is None else torch.as_tensor(np.asarray(known)[rows], dtype=torch.bool)
        s = carrier_samples(power[torch.as_tensor(rows)], noise, k, cfg)
        valid = s["valid"].numpy()
        server = np.where(valid, np.asarray(cell_ids)[rows][s["server"].numpy()], -1)
        maps.append(
            GridMaps(
                freq,
                10.0 * np.log10(np.maximum(s["best_mw"].numpy(), MIN_POWER_MW)),
                server,
                10.0 * np.log10(np.maximum(s["sinr_lin"].numpy(), MIN_POWER_MW)),
                valid,
            )
        )
    return maps


def best_beam_power_from_rsrp(
    rsrp_dbm: np.ndarray,
    pairs_cell: np.ndarray,
    pairs_grid: np.ndarray,
    cell_ids: np.ndarray,
    grid_ids: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Best-beam power matrix ``[num_cells, num_grids]`` [mW] and the known-pair mask from per-pair
    RSRP ``[num_pairs, num_beams]`` [dBm] (NaN past a codebook), e.g. ``predict_rsrp``'s output."""
    power = np.zeros((len(cell_ids), len(grid_ids)))
    known = np.zeros_like(power, dtype=bool)
    c = np.searchsorted(cell_ids, pairs_cell)
    g = np.searchsorted(grid_ids, pairs_grid)
    with np.errstate(invalid="ignore"):
        best = np.nanmax(np.where(np.isfinite(rsrp_dbm), rsrp_dbm, -np.inf), axis=1)
    power[c, g] = np.where(np.isfinite(best), 10.0 ** (best / 10.0), 0.0)
    known[c, g] = True
    return power, known


def _floats(kpis: dict[str, torch.Tensor]) -> dict[str, float]:
    return {k: float(v) for k, v in kpis.items()}
