"""The *field* measurement model: measurements as a real network reports them (SPEC §2, §6; issue 12).

From one trace (paths per receiver point, :mod:`rflscm.sim.paths`) to reported RSRP, effect by effect;
each effect is a field of :class:`FieldConfig` and can be switched off.  Defaults and their sources
are listed in ``docs/DECISIONS.md`` ("Field measurements").

1. **UE samples** — each round draws ``samples_per_grid`` samples per grid, each at a receiver point
   of the grid chosen at random (``positions = "random"``; both rounds draw their own), or every
   traced point equally often (``"all"``, today's ideal regime).
2. **Real antenna** — per-element amplitude [dB] and phase [deg] errors, Gaussian, fixed per cell
   (the same in both rounds), multiply the beam weights; optionally a real element pattern (an MSI
   file) replaces the declared one.  Only the truth sees them: the cells tables keep the nominal array.
3. **Fading** — a sample's beam power is the coherent sum of its point's paths with independent
   uniform phases, |Σ_p √q_pm e^{jφ_p}|², q_pm the path's power through beam m (non-coherent power
   when ``fading`` is off); a grid value is the linear mean of its samples (TS 38.215 §5.1.1: RSRP
   is a linear average).  The phases of one sample are shared by every cell of a (site, carrier)
   and by both beam types.  ``truth/rsrp_noiseless`` holds the fading-free mean over the same
   samples through the real antenna (the noise floor of ``rflscm evaluate``).
4. **Report error** — Gaussian RSRP error per reported value (``accuracy_sigma_db``), 1 dB report
   step, reportable range and threshold r_th: :class:`~rflscm.sim.noise.MeasurementModel`, with the
   same random draws as the ideal regime.
5. **Reporting** — SSB beams detected by SS-SINR against the other cells' same-index SSB on the
   carrier (synchronised bursts) plus noise; optionally only the top-N SSB beams per report;
   CSI-RS (UE-specific) only for the serving cell of each (round, grid, carrier) — the cell with
   the strongest reported SSB beam — and only its top-N beams.  The rule is written to
   ``scenario.yaml`` (``reporting:``) so that models know what a missing beam means.

With every effect off (``FieldConfig.ideal()``) the result equals the ideal regime's bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import pandas as pd
import torch

from rflscm.antenna import sensing_matrix
from rflscm.data import BEAM_TYPES
from rflscm.data.reporting import ReportingRule
from rflscm.errors import ConfigError
from rflscm.sim.noise import MeasurementModel
from rflscm.sim.paths import _CHUNK, _long, path_directions, site_groups, to_dbm

THERMAL_NOISE_DBM_PER_HZ = -174.0
"""Thermal noise density at 290 K [dBm/Hz]."""


@dataclass(frozen=True)
class FieldConfig:
    """Every effect of the field regime (YAML: ``field:`` in the simulation config; sources in DECISIONS)."""

    samples_per_grid: int = 36
    """UE samples averaged per (grid, round): Lee's criterion, 36 samples per local mean (W. C. Y. Lee,
    Mobile Communications Design Fundamentals, 1986; drive-test practice)."""
    positions: Literal["random", "all"] = "random"
    """``random``: each sample at a random traced point of its grid, drawn per round; ``all``: every point
    equally (the ideal regime)."""
    fading: bool = True
    """Coherent sum of paths with random phases per sample (``False``: non-coherent expectation)."""
    accuracy_sigma_db: float = 2.3
    """Per-report RSRP error σ [dB]: TS 38.133 §10.1.2 SS-RSRP absolute accuracy ±4.5 dB (FR1, normal
    conditions) read as a 95 % interval (4.5 / 1.96)."""
    quantization_db: float = 1.0
    """Report step [dB]: TS 38.133 §10.1.6 RSRP report mapping."""
    threshold_dbm: float = -120.0
    """Absolute floor r_th [dBm] on top of the rules below."""
    array_amp_sigma_db: float = 0.5
    """Per-element amplitude error σ [dB], fixed per cell (residual after calibration)."""
    array_phase_sigma_deg: float = 5.0
    """Per-element phase error σ [deg], fixed per cell (residual after calibration)."""
    real_element: str | None = None
    """MSI file of the real element pattern the truth uses (``None``: the declared one)."""
    ssb_detection: Literal["sinr", "threshold"] = "sinr"
    """``sinr``: an SSB beam is reported when its SS-SINR reaches ``ssb_sinr_db``."""
    ssb_sinr_db: float = -6.0
    """SS-SINR detection level [dB]: TS 38.133 §9.2 intra-frequency side condition SSB Ês/Iot ≥ −6 dB."""
    subcarrier_spacing_hz: float = 30e3
    """SCS of the noise per resource element (TS 38.101-1 n78: 30 kHz)."""
    noise_figure_db: float = 9.0
    """UE noise figure [dB] (3GPP TR 38.901 / TR 36.814 evaluation assumption)."""
    ssb_top_n: int | None = None
    """Report only the N strongest SSB beams per (cell, grid) (``None``: every detected beam, as a scanner)."""
    csi_serving_only: bool = True
    """CSI-RS rows only for the serving cell of each (round, grid, carrier) (CSI-RS is UE-specific)."""
    csi_top_n: int | None = 4
    """CSI-RS beams per report: TS 38.214 §5.2.1.4 L1-RSRP reports carry up to 4 (``nrofReportedRS``)."""
    drive_routes: int = 0
    """Drive test: only the grids along this many routes are measured (both rounds drive the same routes);
    0 = every grid (MR-like coverage)."""
    drive_route_grids: int = 80
    """Grids per route: a random walk between neighbouring outdoor grids (streets), without revisits."""

    def __post_init__(self) -> None:
        checks = [
            (self.samples_per_grid >= 1, "`field.samples_per_grid` must be >= 1"),
            (self.positions in ("random", "all"), "`field.positions` must be random or all"),
            (self.accuracy_sigma_db >= 0 and self.quantization_db >= 0, "`field` error and step must be >= 0 dB"),
            (self.array_amp_sigma_db >= 0 and self.array_phase_sigma_deg >= 0, "array errors must be >= 0"),
            (self.ssb_detection in ("sinr", "threshold"), "`field.ssb_detection` must be sinr or threshold"),
            (self.ssb_top_n is None or self.ssb_top_n >= 1, "`field.ssb_top_n` must be >= 1 or null"),
            (self.csi_top_n is None or self.csi_top_n >= 1, "`field.csi_top_n` must be >= 1 or null"),
            (
                self.drive_routes >= 0 and self.drive_route_grids >= 1,
                "`field.drive_routes` >= 0, `drive_route_grids` >= 1",
            ),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"simulation config: {message}.")
        MeasurementModel(self.accuracy_sigma_db, self.quantization_db, self.threshold_dbm)

    @classmethod
    def ideal(cls, sigma_db: float = 2.0, quantization_db: float = 1.0, threshold_dbm: float = -120.0) -> FieldConfig:
        """Every field effect off: the ideal regime's measurements."""
        return cls(
            positions="all",
            fading=False,
            accuracy_sigma_db=sigma_db,
            quantization_db=quantization_db,
            threshold_dbm=threshold_dbm,
            array_amp_sigma_db=0.0,
            array_phase_sigma_deg=0.0,
            ssb_detection="threshold",
            ssb_top_n=None,
            csi_serving_only=False,
            csi_top_n=None,
        )

    @property
    def noise_dbm(self) -> float:
        """Noise power per resource element [dBm]: −174 dBm/Hz + 10 log10(SCS) + NF."""
        return THERMAL_NOISE_DBM_PER_HZ + 10.0 * np.log10(self.subcarrier_spacing_hz) + self.noise_figure_db

    @property
    def measurement_model(self) -> MeasurementModel:
        return MeasurementModel(self.accuracy_sigma_db, self.quantization_db, self.threshold_dbm)

    def reporting(self) -> dict[str, ReportingRule]:
        """The rule this config reports by, for ``scenario.yaml`` (empty when it is the plain threshold)."""
        out = {}
        if self.ssb_detection == "sinr":
            out["ssb"] = ReportingRule("sinr", self.ssb_top_n, self.ssb_sinr_db, round(self.noise_dbm, 2))
        elif self.ssb_top_n is not None:
            out["ssb"] = ReportingRule("top_n", self.ssb_top_n)
        if self.csi_top_n is not None:
            out["csi"] = ReportingRule("top_n", self.csi_top_n, serving_only=self.csi_serving_only)
        elif self.csi_serving_only:
            out["csi"] = ReportingRule("threshold", serving_only=True)
        return out


# ---- samples and the real antenna ---------------------------------------------------------------------------
def draw_samples(
    grid_ids: np.ndarray, points_per_grid: int, config: FieldConfig, rounds: list[int], rng: np.random.Generator
) -> pd.DataFrame:
    """UE samples of every round: ``round``, ``grid_id``, ``point_id``, ``weight`` (share of the grid's
    samples at that point; the weights of a (round, grid) sum to 1)."""
    frames = []
    for rnd in rounds:
        if config.positions == "all":
            counts = np.ones((len(grid_ids), points_per_grid))
        else:
            picks = rng.integers(points_per_grid, size=(len(grid_ids), config.samples_per_grid))
            counts = np.stack([(picks == k).sum(1) for k in range(points_per_grid)], axis=1).astype(float)
        weight = counts / counts.sum(1, keepdims=True)
        g, k = np.nonzero(weight)
        frames.append(
            pd.DataFrame({"round": rnd, "grid_id": grid_ids[g], "point_id": k.astype(np.int16), "weight": weight[g, k]})
        )
    return pd.concat(frames, ignore_index=True)


def array_errors(num_h: int, num_v: int, config: FieldConfig, rng: np.random.Generator) -> torch.Tensor | None:
    """Complex per-element gains ``[num_h, num_v]`` of one real array, or ``None`` without errors."""
    if config.array_amp_sigma_db == 0 and config.array_phase_sigma_deg == 0:
        return None
    amp_db = rng.normal(0.0, config.array_amp_sigma_db, (num_h, num_v))
    phase = np.deg2rad(rng.normal(0.0, config.array_phase_sigma_deg, (num_h, num_v)))
    return torch.as_tensor(10.0 ** (amp_db / 20.0) * np.exp(1j * phase))


def path_beam_power(paths: pd.DataFrame, antenna, codebook, wavelength_m: float, gains) -> np.ndarray:
    """q ``[num_paths, num_beams]`` [mW]: each path's power through each beam of the (real) antenna."""
    out = np.zeros((len(paths), codebook.num_beams))
    if len(paths) == 0:
        return out
    directions = path_directions(paths)
    power = paths["power_lin"].to_numpy(np.float64)
    for start in range(0, len(paths), _CHUNK):
        a = sensing_matrix(
            antenna,
            codebook,
            directions[start : start + _CHUNK],
            wavelength_m,
            dtype=torch.float64,
            element_gains=gains,
        )
        out[start : start + _CHUNK] = a.numpy().T * power[start : start + _CHUNK, None]
    return out


class SampleSums:
    """The samples of one (site, carrier) and round as sparse path incidences.

    ``coherent @ √q`` gives each sample's complex beam amplitude (random path phases), ``mean @ q`` each
    grid's fading-free mean power over its samples; rows of ``coherent`` are grid-major, ``num_samples``
    per grid.
    """

    def __init__(
        self,
        paths: pd.DataFrame,
        grid_ids: np.ndarray,
        samples: pd.DataFrame,
        config: FieldConfig,
        rng: np.random.Generator,
    ) -> None:
        from scipy import sparse

        num_grids, num_paths = len(grid_ids), len(paths)
        g_pos = np.searchsorted(grid_ids, paths["grid_id"].to_numpy(np.int64))
        key = g_pos * 4096 + paths["point_id"].to_numpy(np.int64)
        s_key = np.searchsorted(grid_ids, samples["grid_id"].to_numpy(np.int64)) * 4096 + samples["point_id"].to_numpy()
        weights = pd.Series(samples["weight"].to_numpy(), index=s_key)
        w = weights.reindex(key).fillna(0.0).to_numpy()
        self.mean = sparse.csr_matrix((w, (g_pos, np.arange(num_paths))), shape=(num_grids, num_paths))
        self.coherent = None
        if config.fading:
            k = config.samples_per_grid
            order = np.argsort(key, kind="stable")
            uniq, start, count = np.unique(key[order], return_index=True, return_counts=True)
            # each sample's point: draw it with the same weights the samples table holds
            sample_key = _sample_points(grid_ids, samples, k)  # [num_grids * k]
            pos = np.clip(np.searchsorted(uniq, sample_key), 0, max(len(uniq) - 1, 0))
            has = uniq[pos] == sample_key if len(uniq) else np.zeros(len(sample_key), bool)
            n = np.where(has, count[pos] if len(uniq) else 0, 0)
            rows = np.repeat(np.arange(len(sample_key)), n)
            first = np.repeat(start[pos] if len(uniq) else np.zeros(len(sample_key), int), n)
            cols = order[first + np.arange(len(rows)) - np.repeat(np.cumsum(n) - n, n)]
            phase = np.exp(1j * rng.uniform(0.0, 2.0 * np.pi, len(rows)))
            self.coherent = sparse.csr_matrix((phase, (rows, cols)), shape=(len(sample_key), num_paths))
        self.num_grids, self.k = num_grids, config.samples_per_grid

    def faded(self, q: np.ndarray) -> np.ndarray:
        """Mean over samples of |Σ_p √q e^{jφ}|² ``[num_grids, num_beams]`` [mW]."""
        amp = self.coherent @ np.sqrt(q)  # [num_grids * k, num_beams]
        power = amp.real**2 + amp.imag**2
        return power.reshape(self.num_grids, self.k, -1).mean(axis=1)


def _sample_points(grid_ids: np.ndarray, samples: pd.DataFrame, k: int) -> np.ndarray:
    """Keys (grid position · 4096 + point) of the ``k`` samples of every grid, grid-major, from the weights."""
    g = np.searchsorted(grid_ids, samples["grid_id"].to_numpy(np.int64))
    counts = np.rint(samples["weight"].to_numpy() * k).astype(np.int64)
    keys = np.repeat(g * 4096 + samples["point_id"].to_numpy(np.int64), counts)
    per_grid = np.bincount(np.repeat(g, counts), minlength=len(grid_ids))
    if not (per_grid == k).all():  # weights not multiples of 1/k (positions "all"): cycle through the points
        out = []
        for gi in range(len(grid_ids)):
            pts = samples["point_id"].to_numpy()[g == gi]
            out.append(gi * 4096 + np.resize(pts if len(pts) else np.zeros(1, int), k))
        return np.concatenate(out)
    return keys[np.argsort(np.repeat(g, counts), kind="stable")]


# ---- the whole measurement step ---------------------------------------------------------------------------
def _no_channel_effects(config: FieldConfig) -> bool:
    return (
        config.positions == "all"
        and not config.fading
        and config.real_element is None
        and config.array_amp_sigma_db == 0
        and config.array_phase_sigma_deg == 0
    )


def field_rsrp(
    scenario, paths: pd.DataFrame, points_per_grid: int, config: FieldConfig, rng: np.random.Generator
) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """True grid RSRP of every (round, cell, grid, beam) in the field regime, before report error.

    Args:
        scenario: cells of every round, grids, codebooks (nominal antennas).
        paths: the truth paths (``site_id``, ``freq_hz``, ``grid_id``, ``point_id``, ``power_lin``, AoD).
        points_per_grid: receiver points traced per grid.
        rng: draws samples, array errors and phases (not the report error).

    Returns:
        ``(measured, expected, samples)``: long-form tables like :func:`~rflscm.sim.paths.noiseless_rsrp`
        [dBm] — ``measured`` the faded sample mean through the real antenna, ``expected`` the
        fading-free mean over the same samples through the real antenna — and the samples table
        (:func:`draw_samples`).
    """
    from rflscm.sim.paths import noiseless_rsrp

    grid_ids = scenario.grid_ids()
    samples = draw_samples(grid_ids, points_per_grid, config, scenario.rounds(), rng)
    if _no_channel_effects(config):
        exact = noiseless_rsrp(scenario, paths, points_per_grid)
        return exact, exact, samples
    element = None
    if config.real_element is not None:
        from rflscm.antenna import read_msi

        element = read_msi(config.real_element)
    gains = {}
    for cell_id in scenario.cell_ids():  # fixed per cell: drawn once, in cell order
        array = scenario.antenna(int(cell_id), 1).array
        gains[int(cell_id)] = array_errors(array.num_h, array.num_v, config, rng)
    groups = site_groups(paths)
    measured, expected = [], []
    for rnd in scenario.rounds():
        sums = {
            key: SampleSums(sub, grid_ids, samples[samples["round"] == rnd], config, rng) for key, sub in groups.items()
        }
        for cell_id in scenario.cell_ids():
            row = scenario.cell_row(int(cell_id), rnd)
            key = (int(row["site_id"]), float(row["freq_hz"]))
            antenna = scenario.antenna(int(cell_id), rnd)
            if element is not None:
                antenna = replace(antenna, element=element)
            for beam_type in BEAM_TYPES:
                book = scenario.codebook(int(cell_id), beam_type, rnd)
                if key not in groups:
                    zeros = np.full((len(grid_ids), book.num_beams), -np.inf)
                    measured.append(_long(zeros, rnd, int(cell_id), grid_ids, beam_type))
                    expected.append(measured[-1])
                    continue
                q = path_beam_power(
                    groups[key], antenna, book, scenario.wavelength_m(int(cell_id)), gains[int(cell_id)]
                )
                mean = sums[key].mean @ q
                faded = sums[key].faded(q) if config.fading else mean
                measured.append(_long(to_dbm(faded), rnd, int(cell_id), grid_ids, beam_type))
                expected.append(_long(to_dbm(mean), rnd, int(cell_id), grid_ids, beam_type))
    return pd.concat(measured, ignore_index=True), pd.concat(expected, ignore_index=True), samples


def report(true_rsrp: pd.DataFrame, scenario, config: FieldConfig, rng: np.random.Generator) -> pd.DataFrame:
    """The measurements table from the true grid RSRP (long form, as :func:`field_rsrp` returns it).

    Report error and threshold (:class:`MeasurementModel`, one normal draw per row in table order, as
    the ideal regime), then SSB detection by SS-SINR and top-N, the (cell, grid) pairs with a reported
    SSB beam, the serving cell's CSI-RS and its top-N.  Missing beams of kept reports are NaN rows.
    """
    table = true_rsrp.assign(rsrp_dbm=config.measurement_model.apply(true_rsrp["rsrp_dbm"].to_numpy(), rng))
    freq = scenario.cells[1].set_index("cell_id")["freq_hz"]
    table["freq_hz"] = freq.loc[table["cell_id"]].to_numpy()
    ssb = (table["beam_type"] == "ssb").to_numpy()
    if config.ssb_detection == "sinr":
        with np.errstate(divide="ignore"):
            lin = np.where(np.isfinite(true_rsrp["rsrp_dbm"]), 10.0 ** (true_rsrp["rsrp_dbm"].to_numpy() / 10.0), 0.0)
        lin = np.where(ssb, lin, 0.0)
        keys = [table["round"], table["freq_hz"], table["grid_id"], table["beam_id"]]
        total = pd.Series(lin).groupby(keys).transform("sum").to_numpy()
        sinr_db = 10.0 * np.log10(np.maximum(lin, 1e-300) / (total - lin + 10.0 ** (config.noise_dbm / 10.0)))
        table.loc[ssb & (sinr_db < config.ssb_sinr_db), "rsrp_dbm"] = np.nan
    if config.ssb_top_n is not None:
        _keep_top(table, ssb, config.ssb_top_n)
    heard = table["rsrp_dbm"].notna() & ssb
    detected = heard.groupby([table["round"], table["cell_id"], table["grid_id"]], sort=False).transform("any")
    table = table[detected.to_numpy()].reset_index(drop=True)
    csi = (table["beam_type"] == "csi").to_numpy()
    if config.csi_serving_only:
        best = table["rsrp_dbm"].where(table["beam_type"] == "ssb")
        per_cell = best.groupby([table["round"], table["freq_hz"], table["grid_id"], table["cell_id"]]).max()
        per_cell = per_cell.reset_index().sort_values(["rsrp_dbm", "cell_id"], ascending=[False, True])
        serving = per_cell.drop_duplicates(["round", "freq_hz", "grid_id"])
        key = pd.MultiIndex.from_frame(table[["round", "grid_id", "cell_id"]])
        is_serving = key.isin(pd.MultiIndex.from_frame(serving[["round", "grid_id", "cell_id"]]))
        table = table[~csi | np.asarray(is_serving)].reset_index(drop=True)
        csi = (table["beam_type"] == "csi").to_numpy()
    if config.csi_top_n is not None:
        _keep_top(table, csi, config.csi_top_n)
    if config.drive_routes > 0:
        route = drive_route(scenario.grids, config.drive_routes, config.drive_route_grids, rng)
        table = table[table["grid_id"].isin(route).to_numpy()].reset_index(drop=True)
    return table.drop(columns="freq_hz")


def drive_route(grids: pd.DataFrame, num_routes: int, length: int, rng: np.random.Generator) -> np.ndarray:
    """Grid ids ``[n]`` along ``num_routes`` random walks of up to ``length`` grids between neighbouring grids
    (centres within 1.5 grid sizes: the street network of outdoor grids), never revisiting a grid."""
    from scipy.spatial import cKDTree

    xy = grids[["x", "y"]].to_numpy(np.float64)
    ids = grids["grid_id"].to_numpy()
    if len(ids) < 2:
        return ids
    step = float(np.median(cKDTree(xy).query(xy, k=2)[0][:, 1]))
    neighbours = cKDTree(xy).query_ball_point(xy, r=1.5 * step)
    visited = np.zeros(len(ids), dtype=bool)
    for _ in range(num_routes):
        here = int(rng.choice(np.flatnonzero(~visited))) if (~visited).any() else 0
        for _ in range(length):
            visited[here] = True
            options = [n for n in neighbours[here] if not visited[n]]
            if not options:
                break
            here = int(rng.choice(options))
    return ids[visited]


def _keep_top(table: pd.DataFrame, rows: np.ndarray, top_n: int) -> None:
    """In place: NaN every reported value of ``rows`` outside the ``top_n`` strongest of its report."""
    value = table["rsrp_dbm"].where(rows)
    rank = value.groupby([table["round"], table["cell_id"], table["grid_id"], table["beam_type"]]).rank(
        method="first", ascending=False
    )
    table.loc[rows & (rank > top_n).to_numpy(), "rsrp_dbm"] = np.nan
