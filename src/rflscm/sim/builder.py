"""Build a complete scenario with ground truth from a scene backend (SPEC §6, `rflscm simulate`).

Flow: choose sites on rooftops → cells (sites × sectors × carriers) → outdoor
10 m grids with jittered receiver points → one trace per (site, carrier) →
``truth/`` (paths, true APS, noiseless RSRP) → round-2 antenna changes →
noisy, quantised, thresholded measurements → a scenario folder that
:func:`rflscm.data.load_scenario` accepts.  Every random choice draws from one
seeded generator, so the same config and seed give identical files (with a
deterministic backend such as :class:`~rflscm.sim.procedural.ProceduralCity`).
"""

from __future__ import annotations

import dataclasses
import inspect
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd

from rflscm.antenna import DFTCodebook, SSBCodebook, wavelength_of
from rflscm.antenna.codebook import Codebook
from rflscm.config import to_dict
from rflscm.data import PointCloud, Scenario, ScenarioMeta, empty_measurements, load_scenario, save_scenario
from rflscm.errors import ConfigError
from rflscm.geometry import AngleGrid
from rflscm.runtime import Mapper
from rflscm.sim.backend import SceneBackend
from rflscm.sim.field import FieldConfig
from rflscm.sim.noise import MeasurementModel
from rflscm.sim.paths import PATHS_FILE
from rflscm.sim.stream import PathStore

ASPRS_BUILDING = 6
CODEBOOKS: dict[str, Codebook] = {
    "ssb8": SSBCodebook(),
    "csi32": DFTCodebook(),
    "ssb8_b": SSBCodebook(azimuths_deg=(-50.0, -20.0, 10.0, 40.0), tilts_deg=(3.0, 12.0), active_h=4, active_v=4),
    "csi32_b": DFTCodebook(beams_v=(1, 2, 3, 4)),
}
"""Codebooks of every simulated scenario: round 1 uses ``ssb8``/``csi32``; method (a) switches a cell
to ``ssb8_b`` (beams turned and tilted, narrower vertically) and ``csi32_b`` (beams one step further down)."""
_BACKEND_KINDS = {"ProceduralCity": "procedural", "SionnaSceneBackend": "sionna"}
ROUND1_CODEBOOKS = ("ssb8", "csi32")
ROUND2_CODEBOOKS = ("ssb8_b", "csi32_b")


@dataclass(frozen=True)
class SimulationConfig:
    """Everything `rflscm simulate` decides (YAML keys = field names; unknown keys are rejected)."""

    name: str = "simulated"
    description: str = ""
    seed: int = 0
    # --- sites and cells ---
    num_sites: int = 7
    sites: tuple[tuple[float, ...], ...] = ()
    """Explicit antenna positions ``[[x, y, z], …]`` [m] (z above the scene's zero); overrides ``num_sites``."""
    area_center_xy: tuple[float, ...] = ()
    """Centre of the measured area [m]; default: centre of the scene."""
    site_radius_m: float = 300.0
    """Sites are picked among rooftops within this distance of the area centre [m]."""
    site_min_roof_quantile: float = 0.5
    """Sites go on roofs at least this tall among the candidates (0 = any roof, 0.5 = the taller half)."""
    site_placement: Literal["edge", "center"] = "edge"
    """``edge``: move each site from its roof centre towards the area centre, to the roof edge."""
    roof_setback_m: float = 1.5
    site_height_above_roof_m: float = 3.0
    sector_azimuths_deg: tuple[float, ...] = (0.0, 120.0, 240.0)
    azimuth_jitter_deg: float = 10.0
    """Each sector's azimuth is drawn uniformly within ± this of its nominal value [deg]."""
    mech_tilt_deg: float = 3.0
    elec_tilt_deg: float = 3.0
    tx_power_dbm: float = 15.0
    carriers_hz: tuple[float, ...] = (3.5e9, 2.1e9)
    """Carriers [Hz]; the first is the primary. Every carrier gets an 8 × 4 array designed at it."""
    # --- grids ---
    grid_size_m: float = 10.0
    points_per_grid: int = 4
    ue_height_m: float = 1.5
    max_grids: int = 800
    grid_radius_m: float | None = None
    """Keep only grids within this distance of the area centre [m] (the nearest ``max_grids`` anyway)."""
    trace_range_m: float | None = None
    """Each site is traced only to the receivers within this horizontal distance [m] (farther ones get no path
    from it: its cells are never heard there); ``null`` traces every receiver from every site.  Makes the
    trace, the truth and the measurements grow linearly with the sites (set for a grown city, see
    :func:`grow_procedural`)."""
    # --- measurement model ---
    measurements: Literal["ideal", "field"] = "ideal"
    """``ideal``: the keys below (noise on the expectation over all points); ``field``: :class:`FieldConfig`
    (``field_model:`` block; its own error, step and threshold replace the keys below)."""
    field_model: FieldConfig = field(default_factory=FieldConfig)
    """The field regime's effects (used with ``measurements: field``; see :mod:`rflscm.sim.field`)."""
    noise_sigma_db: float = 2.0
    quantization_db: float = 1.0
    rsrp_threshold_dbm: float = -120.0
    detect_on: Literal["ssb", "any"] = "ssb"
    """A (cell, grid) pair is measured when one of its SSB beams (``ssb``) or of any beam (``any``) is reported."""
    # --- round 2 (SPEC §5) ---
    round2_change_fraction: float = 1.0 / 3.0
    """Fraction of each carrier's cells changed in round 2."""
    round2_codebook_fraction: float = 0.75
    """Share of the changed cells that get method (a), another codebook; the rest get method (b), a rotation."""
    rotation_azimuth_deg: tuple[float, ...] = (-15.0, -10.0, -7.0, 7.0, 10.0, 15.0)
    rotation_tilt_deg: tuple[float, ...] = (0.0, 2.0, 4.0)
    # --- point cloud ---
    point_cloud_points_per_m2: float = 0.25
    point_cloud_noise_m: float = 0.05
    point_cloud_margin_m: float = 50.0
    """The cloud is cropped to the box around sites and grids grown by this margin [m]."""
    # --- truth ---
    angle_grid: AngleGrid = field(default_factory=AngleGrid)
    truth_floor_db: float | None = 60.0
    """Paths more than this below the strongest path of their receiver are dropped [dB]."""
    truth_rsrp_margin_db: float | None = 10.0
    """``truth/rsrp_noiseless`` leaves out (round, cell, grid) pairs whose strongest beam is more than this
    below the reporting threshold (never reportable); ``null`` keeps every pair."""
    backend_options: dict[str, Any] = field(default_factory=dict)
    """Keyword arguments of the backend (e.g. ``max_depth`` for Sionna, ``num_buildings`` for procedural)."""

    def __post_init__(self) -> None:
        checks = [
            (self.seed >= 0, "`seed` must be >= 0"),
            (self.num_sites >= 1 or bool(self.sites), "`num_sites` must be >= 1"),
            (all(len(s) == 3 for s in self.sites), "`sites` rows must be [x, y, z]"),
            (len(self.area_center_xy) in (0, 2), "`area_center_xy` must be [x, y] or empty"),
            (1 <= len(self.sector_azimuths_deg) <= 10, "`sector_azimuths_deg` needs 1…10 sectors"),
            (1 <= len(self.carriers_hz) <= 10, "`carriers_hz` needs 1…10 carriers"),
            (self.grid_size_m > 0 and self.points_per_grid >= 1, "`grid_size_m` > 0 and `points_per_grid` >= 1"),
            (self.max_grids >= 1, "`max_grids` must be >= 1"),
            (0.0 <= self.round2_change_fraction <= 1.0, "`round2_change_fraction` must be in 0…1"),
            (0.0 <= self.site_min_roof_quantile <= 1.0, "`site_min_roof_quantile` must be in 0…1"),
            (0.0 <= self.round2_codebook_fraction <= 1.0, "`round2_codebook_fraction` must be in 0…1"),
            (bool(self.rotation_azimuth_deg) and bool(self.rotation_tilt_deg), "rotation lists must not be empty"),
            (self.point_cloud_points_per_m2 > 0, "`point_cloud_points_per_m2` must be > 0"),
            (self.trace_range_m is None or self.trace_range_m > 0, "`trace_range_m` must be > 0 m or null"),
        ]
        for ok, message in checks:
            if not ok:
                raise ConfigError(f"simulation config: {message}.")
        for i, freq in enumerate(self.carriers_hz):
            if freq < 1e8:
                raise ConfigError(
                    f"simulation config: `carriers_hz[{i}]` = {freq:g} looks like MHz or GHz; give carriers in Hz, "
                    f"e.g. 3.5e9 for 3.5 GHz."
                )
        if len(set(self.carriers_hz)) != len(self.carriers_hz):
            raise ConfigError(f"simulation config: `carriers_hz` lists a carrier twice ({self.carriers_hz}).")
        MeasurementModel(self.noise_sigma_db, self.quantization_db, self.rsrp_threshold_dbm)

    @property
    def measurement_model(self) -> MeasurementModel:
        return MeasurementModel(self.noise_sigma_db, self.quantization_db, self.rsrp_threshold_dbm)

    @property
    def threshold_dbm(self) -> float:
        """The reporting threshold r_th of the regime in use [dBm]."""
        return self.field_model.threshold_dbm if self.measurements == "field" else self.rsrp_threshold_dbm


GROWN_TRACE_RANGE_M = 500.0
"""Trace range of a grown procedural city [m].  On the grown 19-site city traced without a range, 1.1 % of the
detected (cell, grid) pairs lay beyond 500 m and 0.06 % beyond 600 m (docs/DECISIONS.md, issue 29)."""


# ---- layout: sites, cells, grids ---------------------------------------------------------------------
def grow_procedural(config: SimulationConfig, scene: str, scale_grids: bool = True) -> SimulationConfig:
    """``config`` for a procedural city that grows with ``num_sites`` at the default density.

    Up to the default site count (7), or with explicit ``sites``, ``config`` is returned unchanged.  Beyond it,
    by the factor f = num_sites / 7: the scene's area and building count × f (``backend_options`` ``size_m``,
    ``num_buildings``; values set there win), ``site_radius_m`` × √f and, when ``scale_grids``, ``max_grids``
    × f, so that cells (3 per site and carrier) and grids both grow linearly with the sites.  ``trace_range_m``,
    when not set, becomes :data:`GROWN_TRACE_RANGE_M`, so that a cell is heard over a bounded area and the
    trace, the truth and the measurements grow linearly too (not with the square of the sites).
    """
    from rflscm.sim.procedural import grown_scene_options

    base = SimulationConfig()
    if config.sites or config.num_sites <= base.num_sites:
        return config
    factor = config.num_sites / base.num_sites
    options = {**grown_scene_options(scene, config.num_sites, base.num_sites), **config.backend_options}
    return dataclasses.replace(
        config,
        backend_options=options,
        site_radius_m=config.site_radius_m * float(np.sqrt(factor)),
        max_grids=round(config.max_grids * factor) if scale_grids else config.max_grids,
        trace_range_m=config.trace_range_m if config.trace_range_m is not None else GROWN_TRACE_RANGE_M,
    )


def area_center(backend: SceneBackend, config: SimulationConfig) -> np.ndarray:
    if config.area_center_xy:
        return np.asarray(config.area_center_xy, dtype=np.float64)
    lo, hi = backend.bounds()
    return 0.5 * (np.asarray(lo[:2]) + np.asarray(hi[:2]))


def choose_sites(
    backend: SceneBackend, config: SimulationConfig, rng: np.random.Generator, cloud: PointCloud | None = None
) -> np.ndarray:
    """Antenna positions ``[num_sites, 3]`` [m]: explicit, or rooftops spread by farthest-point sampling.

    Candidates are the backend's rooftops within ``site_radius_m`` of the area centre, on the taller
    roofs (at least the ``site_min_roof_quantile`` of their heights), as operators choose.  With
    ``site_placement = "edge"`` a site moves towards the area centre to its roof's edge; its base is then
    the higher of the candidate's roof and the highest building point of ``cloud`` within 3 m, so that
    an antenna never ends up inside a taller part of the building; plus ``site_height_above_roof_m``.
    """
    if config.sites:
        return np.asarray(config.sites, dtype=np.float64)
    centre = area_center(backend, config)
    roofs = np.asarray(backend.rooftops(), dtype=np.float64).reshape(-1, 3)
    dist = np.linalg.norm(roofs[:, :2] - centre, axis=1)
    pool = roofs[dist <= config.site_radius_m]
    if len(pool) >= config.num_sites:
        tall = pool[:, 2] >= np.quantile(pool[:, 2], config.site_min_roof_quantile)
        pool = pool[tall] if tall.sum() >= config.num_sites else pool
    if len(pool) < config.num_sites:
        pool = roofs[np.argsort(dist)[: config.num_sites]]
    if len(pool) < config.num_sites:
        raise ConfigError(
            f"the scene has only {len(roofs)} rooftop candidates for {config.num_sites} sites; "
            f"ask for fewer sites (--sites) or give `sites` in the config."
        )
    chosen = [int(rng.integers(len(pool)))]
    gap = np.linalg.norm(pool[:, :2] - pool[chosen[0], :2], axis=1)
    for _ in range(config.num_sites - 1):
        chosen.append(int(np.argmax(gap)))
        gap = np.minimum(gap, np.linalg.norm(pool[:, :2] - pool[chosen[-1], :2], axis=1))
    sites = pool[chosen].copy()
    if config.site_placement == "edge":
        sites[:, :2] = _towards_roof_edge(backend, sites[:, :2], centre, config.roof_setback_m)
        if cloud is not None:
            sites[:, 2] = np.maximum(sites[:, 2], _surface_height(cloud, sites[:, :2], default=sites[:, 2]))
    sites[:, 2] += config.site_height_above_roof_m
    return sites


def _surface_height(cloud: PointCloud, xy: np.ndarray, default: np.ndarray, radius_m: float = 3.0) -> np.ndarray:
    """Highest building point ``[n]`` [m] within ``radius_m`` of each ``xy [n, 2]`` (``default`` where none)."""
    from scipy.spatial import cKDTree

    building = cloud.xyz[cloud.classification == ASPRS_BUILDING]
    if len(building) == 0:
        return np.asarray(default, dtype=np.float64)
    near = cKDTree(building[:, :2]).query_ball_point(xy, r=radius_m)
    return np.array([building[idx, 2].max() if idx else d for idx, d in zip(near, default, strict=True)])


def _towards_roof_edge(backend: SceneBackend, xy: np.ndarray, centre: np.ndarray, setback_m: float) -> np.ndarray:
    """Move roof points ``[n, 2]`` towards ``centre`` until ``setback_m`` before their roof's edge."""
    heading = centre - xy
    norm = np.linalg.norm(heading, axis=1, keepdims=True)
    heading = np.where(norm > 1e-6, heading / np.maximum(norm, 1e-6), np.array([1.0, 0.0]))
    steps = np.arange(0.0, 80.0, 0.5)  # [num_steps] m
    probe = xy[:, None, :] + steps[None, :, None] * heading[:, None, :]  # [n, num_steps, 2]
    outdoor = backend.is_outdoor(probe.reshape(-1, 2)).reshape(len(xy), len(steps))
    first_out = np.where(outdoor.any(axis=1), outdoor.argmax(axis=1), 0)
    travel = np.maximum(steps[first_out] - setback_m, 0.0)
    return xy + travel[:, None] * heading


def make_cells(sites: np.ndarray, config: SimulationConfig, rng: np.random.Generator) -> pd.DataFrame:
    """Round-1 cells table: ``cell_id = 100·site_id + 10·carrier_index + sector`` (site ids from 1)."""
    n_sec = len(config.sector_azimuths_deg)
    jitter = rng.uniform(-config.azimuth_jitter_deg, config.azimuth_jitter_deg, (len(sites), n_sec))
    rows = []
    for s, pos in enumerate(sites):
        for c, freq in enumerate(config.carriers_hz):
            wl = wavelength_of(freq)
            for k, az in enumerate(config.sector_azimuths_deg):
                rows.append(
                    {
                        "cell_id": 100 * (s + 1) + 10 * c + k,
                        "site_id": s + 1,
                        "x": pos[0],
                        "y": pos[1],
                        "z": pos[2],
                        "azimuth_deg": float(np.round((az + jitter[s, k]) % 360.0, 1)),
                        "mech_tilt_deg": config.mech_tilt_deg,
                        "elec_tilt_deg": config.elec_tilt_deg,
                        "freq_hz": float(freq),
                        "tx_power_dbm": config.tx_power_dbm,
                        "array_nh": 8,
                        "array_nv": 4,
                        "spacing_h_m": 0.5 * wl,
                        "spacing_v_m": 0.7 * wl,
                        "ssb_codebook": ROUND1_CODEBOOKS[0],
                        "csi_codebook": ROUND1_CODEBOOKS[1],
                        "element": "tr38901",
                    }
                )
    return pd.DataFrame(rows)


def make_round2(
    cells: pd.DataFrame, config: SimulationConfig, rng: np.random.Generator
) -> tuple[pd.DataFrame, list[dict]]:
    """Round-2 cells and the change log: per carrier, a fraction of cells gets method (a) or (b)."""
    round2 = cells.copy()
    changes: list[dict] = []
    for freq in config.carriers_hz:
        ids = cells.loc[cells["freq_hz"] == freq, "cell_id"].to_numpy()
        num = int(round(config.round2_change_fraction * len(ids)))
        picked = np.sort(rng.choice(ids, size=num, replace=False)) if num else np.zeros(0, dtype=int)
        num_a = int(round(config.round2_codebook_fraction * num))
        methods = np.array(["a"] * num_a + ["b"] * (num - num_a))
        rng.shuffle(methods)
        for cell_id, method in zip(picked, methods, strict=True):
            row = round2.index[round2["cell_id"] == cell_id][0]
            change: dict[str, Any] = {"cell_id": int(cell_id), "method": str(method)}
            if method == "a":
                round2.loc[row, ["ssb_codebook", "csi_codebook"]] = list(ROUND2_CODEBOOKS)
                change.update(ssb_codebook=ROUND2_CODEBOOKS[0], csi_codebook=ROUND2_CODEBOOKS[1])
            else:
                d_az = float(rng.choice(config.rotation_azimuth_deg))
                d_tilt = float(rng.choice(config.rotation_tilt_deg))
                round2.loc[row, "azimuth_deg"] = float((cells.loc[row, "azimuth_deg"] + d_az) % 360.0)
                round2.loc[row, "mech_tilt_deg"] = float(np.clip(cells.loc[row, "mech_tilt_deg"] + d_tilt, -90, 90))
                change.update(d_azimuth_deg=d_az, d_mech_tilt_deg=d_tilt)
            changes.append(change)
    return round2, changes


def make_grids(backend: SceneBackend, config: SimulationConfig, centre: np.ndarray) -> pd.DataFrame:
    """Outdoor grid cells nearest ``centre``: ``grid_id`` (lattice index), ``x``, ``y``, ``z`` (UE height) [m]."""
    g = config.grid_size_m
    lo, hi = (np.asarray(b, dtype=np.float64) for b in backend.bounds())
    reach = config.grid_radius_m or 3.0 * g * np.sqrt(config.max_grids)
    i0, i1 = np.floor((max(lo[0], centre[0] - reach)) / g), np.ceil((min(hi[0], centre[0] + reach)) / g)
    j0, j1 = np.floor((max(lo[1], centre[1] - reach)) / g), np.ceil((min(hi[1], centre[1] + reach)) / g)
    ii, jj = np.meshgrid(np.arange(i0, i1), np.arange(j0, j1), indexing="xy")
    xy = np.column_stack([(ii.ravel() + 0.5) * g, (jj.ravel() + 0.5) * g])
    inside = (xy >= lo[:2] + g / 2).all(axis=1) & (xy <= hi[:2] - g / 2).all(axis=1)
    dist = np.linalg.norm(xy - centre, axis=1)
    ok = inside & backend.is_outdoor(xy) & (dist <= reach)
    keep = np.flatnonzero(ok)[np.argsort(dist[ok], kind="stable")[: config.max_grids]]
    if len(keep) == 0:
        raise ConfigError("no outdoor grid lies in the scene near the area centre; check `area_center_xy`.")
    cols = np.round(xy[keep, 0] / g - 0.5).astype(np.int64)
    rows = np.round(xy[keep, 1] / g - 0.5).astype(np.int64)
    grid_id = (rows - rows.min()) * (cols.max() - cols.min() + 1) + (cols - cols.min())
    z = backend.ground_height(xy[keep]) + config.ue_height_m
    return pd.DataFrame({"grid_id": grid_id, "x": xy[keep, 0], "y": xy[keep, 1], "z": z}).sort_values(
        "grid_id", ignore_index=True
    )


def receiver_points(backend: SceneBackend, grids: pd.DataFrame, config: SimulationConfig, rng) -> np.ndarray:
    """Receivers ``[num_grids * K, 3]`` (grid-major): K outdoor points jittered inside each grid at UE height."""
    k, g = config.points_per_grid, config.grid_size_m
    centre = np.repeat(grids[["x", "y"]].to_numpy(), k, axis=0)
    xy = centre + rng.uniform(-g / 2, g / 2, centre.shape)
    for _ in range(20):  # resample points that fell inside a building
        bad = ~backend.is_outdoor(xy)
        if not bad.any():
            break
        xy[bad] = centre[bad] + rng.uniform(-g / 2, g / 2, (int(bad.sum()), 2))
    bad = ~backend.is_outdoor(xy)
    xy[bad] = centre[bad]
    return np.column_stack([xy, backend.ground_height(xy) + config.ue_height_m])


# ---- tracing ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class BackendSpec:
    """How to build a scene backend (:func:`rflscm.sim.make_backend`'s arguments): a worker process builds its
    own from this, once, instead of receiving the driver's (a Sionna scene does not pickle)."""

    name: str
    scene: str | None = None
    seed: int = 0
    device: str = "cpu"
    options: dict[str, Any] = field(default_factory=dict)

    def build(self) -> SceneBackend:
        from rflscm.sim import make_backend

        return make_backend(self.name, self.scene, seed=self.seed, device=self.device, options=self.options)


@dataclass(frozen=True)
class TraceJob:
    """One (site, carrier) to trace: ``site`` and ``carrier`` are indices (0-based), ``receivers`` the indices of
    the receiver points within range (``None``: all of them)."""

    site: int
    carrier: int
    freq_hz: float
    tx: np.ndarray
    receivers: np.ndarray | None
    seed: int


@dataclass(frozen=True)
class TraceSetup:
    """What every trace of a build shares: the receivers ``[num_grids * K, 3]`` (grid-major), their grids' ids
    ``[num_grids]``, K, and the truth floor of :func:`rflscm.sim.paths.trim_paths`."""

    rx: np.ndarray
    grid_ids: np.ndarray
    points_per_grid: int
    truth_floor_db: float | None


def trace_job(
    backend: SceneBackend, setup: TraceSetup, job: TraceJob, progress: Callable[[int, int], None] | None = None
) -> tuple[pd.DataFrame, float]:
    """One (site, carrier)'s trimmed paths in the columns of ``truth/paths.parquet``, and the trace's seconds."""
    from rflscm.sim.paths import trim_paths
    from rflscm.sim.stream import PATH_TABLE_COLUMNS

    start = time.perf_counter()
    near = job.receivers
    if near is not None and len(near) == 0:  # no receiver within range of this site
        from rflscm.sim.backend import empty_path_table

        table = empty_path_table()
    else:
        kwargs = {} if progress is None else {"progress": progress}
        table = backend.trace(
            job.tx, setup.rx if near is None else setup.rx[near], job.freq_hz, seed=job.seed, **kwargs
        )
    seconds = time.perf_counter() - start
    rx_index = table["rx_index"].to_numpy()
    if near is not None:
        rx_index = near[rx_index]
    k = setup.points_per_grid
    table = table.drop(columns="rx_index").assign(
        site_id=np.int32(job.site + 1),
        freq_hz=float(job.freq_hz),
        grid_id=setup.grid_ids[rx_index // k],
        point_id=(rx_index % k).astype(np.int16),
    )
    return trim_paths(table, setup.truth_floor_db)[PATH_TABLE_COLUMNS], seconds


_WORKER_BACKEND: list[tuple[BackendSpec, SceneBackend]] = []  # a worker's backend, built on its first job


def trace_in_worker(spec: BackendSpec, setup: TraceSetup, job: TraceJob) -> tuple[pd.DataFrame, float]:
    """:func:`trace_job` on this process's backend of ``spec`` (built once per process)."""
    if not _WORKER_BACKEND or _WORKER_BACKEND[0][0] != spec:
        _WORKER_BACKEND[:] = [(spec, spec.build())]
    return trace_job(_WORKER_BACKEND[0][1], setup, job)


def trace_all(
    backend: SceneBackend,
    sites: np.ndarray,
    rx: np.ndarray,
    grid_ids: np.ndarray,
    config: SimulationConfig,
    progress: bool = True,
    sink: Callable[[int, float, pd.DataFrame], None] | None = None,
    mapper: Mapper | None = None,
    spec: BackendSpec | None = None,
) -> tuple[pd.DataFrame | None, dict[str, float]]:
    """One trace per (site, carrier) → the paths table of ``truth/paths.parquet`` and timing facts.

    With ``sink``, each (site, carrier)'s trimmed paths go to ``sink(site_id, freq_hz, table)`` as they are
    traced and the table returned is ``None`` (only one trace is in memory at a time, plus those a parallel
    ``mapper`` has finished ahead of it).  With ``mapper`` and ``spec`` the traces run on the mapper's workers,
    each on its own backend built from ``spec`` (the same scene, so the same paths); the sink still receives them
    in site and carrier order.  ``trace_seconds`` is the traces' own time, summed over workers;
    ``trace_wall_seconds`` the loop's wall time."""
    from functools import partial

    from tqdm.auto import tqdm

    setup = TraceSetup(rx, np.asarray(grid_ids), config.points_per_grid, config.truth_floor_db)
    in_range: list[np.ndarray | None] = [None] * len(sites)
    if config.trace_range_m is not None:
        in_range = [np.flatnonzero(np.hypot(rx[:, 0] - s[0], rx[:, 1] - s[1]) <= config.trace_range_m) for s in sites]
    jobs = [
        TraceJob(s, c, float(f), np.asarray(sites[s]), in_range[s], int(config.seed * 1000 + 10 * s + c))
        for s in range(len(sites))
        for c, f in enumerate(config.carriers_hz)
    ]
    parallel = mapper is not None and mapper is not map
    if parallel and spec is None:
        raise ValueError("trace_all: a mapper other than map needs the backend's spec")
    takes_progress = "progress" in inspect.signature(backend.trace).parameters
    tables, seconds, num_paths = [], 0.0, 0
    wall = time.perf_counter()
    desc = f"tracing {backend.name}"
    with tqdm(total=len(jobs), desc=desc, unit="trace", disable=not progress, leave=True) as bar:

        def serial(job: TraceJob) -> tuple[pd.DataFrame, float]:
            label = f"site {job.site + 1}, {job.freq_hz / 1e9:g} GHz"
            bar.set_postfix_str(label)
            report = None
            if takes_progress and progress:

                def report(done: int, total: int) -> None:
                    bar.set_postfix_str(f"{label}, rx {done}/{total}")

            return trace_job(backend, setup, job, report)

        if mapper is not None and spec is not None and parallel:
            run = mapper(partial(trace_in_worker, spec, setup), jobs)
        else:
            run = map(serial, jobs)
        for job, (table, took) in zip(jobs, run, strict=True):
            seconds += took
            num_paths += len(table)
            if sink is None:
                tables.append(table)
            else:
                sink(job.site + 1, job.freq_hz, table)
            bar.update(1)
    paths = pd.concat(tables, ignore_index=True) if sink is None else None
    traced = sum(len(rx) if job.receivers is None else len(job.receivers) for job in jobs)
    stats = {
        "trace_seconds": seconds,
        "trace_wall_seconds": time.perf_counter() - wall,
        "seconds_per_1000_rx_per_carrier": 1000.0 * seconds / max(traced, 1),
        "paths_per_grid": num_paths / max(len(jobs) * len(grid_ids), 1),
    }
    return paths, stats


# ---- the whole build ---------------------------------------------------------------------------------------
def build_scenario(
    backend: SceneBackend,
    config: SimulationConfig,
    out_dir: str | Path,
    progress: bool = True,
    scene: str | None = None,
    stats: dict[str, float] | None = None,
    mapper: Mapper = map,
    spec: BackendSpec | None = None,
) -> Path:
    """Simulate a scenario with ground truth into ``out_dir`` (created; must be empty or absent).

    Returns the folder.  Writes scenario.yaml (with a ``simulation:`` block), cells of rounds 1 and
    2, grids, measurements (both rounds), a PLY point cloud and ``truth/`` (paths, APS, noiseless
    RSRP); the result is validated with :func:`rflscm.data.load_scenario`.  ``stats``, when given,
    receives timings and counts (kept out of the files so that they are reproducible).  ``mapper``
    (with ``spec``, the backend's recipe): the traces and the ideal regime's noiseless RSRP run on its
    workers (:func:`trace_all`, :func:`rflscm.sim.stream.stream_ideal`); the files are the same.
    """
    out = Path(out_dir)
    if out.exists() and any(out.iterdir()):
        raise ConfigError(f"{out}: folder exists and is not empty; choose another --out or pass --force.")
    rng = np.random.default_rng(config.seed)
    centre = area_center(backend, config)
    scan = PointCloud(
        *backend.sample_point_cloud(config.point_cloud_points_per_m2, config.point_cloud_noise_m, config.seed)
    )
    sites = choose_sites(backend, config, rng, scan)
    cells1 = make_cells(sites, config, rng)
    cells2, changes = make_round2(cells1, config, rng)
    grids = make_grids(backend, config, centre)
    rx = receiver_points(backend, grids, config, rng)
    out.mkdir(parents=True, exist_ok=True)
    from rflscm.sim.stream import ParquetAppender, SpilledPaths, compact_paths

    # Each (site, carrier)'s paths go to truth/paths.parquet and to a spill folder as they are traced, so
    # that only one trace is in memory; the measurement step reads them back one (site, carrier) at a time.
    store = SpilledPaths(out / ".trace")
    (out / "truth").mkdir(parents=True, exist_ok=True)
    paths_file = ParquetAppender(out / "truth" / PATHS_FILE, compact_paths(_empty_paths()))

    def keep(site_id: int, freq_hz: float, table: pd.DataFrame) -> None:
        store.add(site_id, freq_hz, table)
        paths_file.append(compact_paths(table))

    try:
        _, trace_stats = trace_all(
            backend, sites, rx, grids["grid_id"].to_numpy(), config, progress, sink=keep, mapper=mapper, spec=spec
        )
    finally:
        paths_file.close()
    del rx
    cloud = _crop(scan, config, sites, grids)
    del scan

    meta = ScenarioMeta(
        name=config.name,
        description=config.description or f"simulated with rflscm ({backend.name})",
        frequencies_hz=tuple(float(f) for f in config.carriers_hz),
        codebooks=dict(CODEBOOKS),
        rounds={1: "cells_round1.parquet", 2: "cells_round2.parquet"},
        grids="grids.parquet",
        measurements="measurements.parquet",
        rsrp_threshold_dbm=config.threshold_dbm,
        point_cloud="point_cloud.ply",
        truth="truth",
        simulation=_provenance(backend, config, scene, changes),
    )
    scenario = Scenario(out.resolve(), meta, {1: cells1, 2: cells2}, grids, empty_measurements(), cloud)
    scenario = _normalised(scenario)
    try:
        write_measurements(scenario, store, config, rng, out, paths_written=True, mapper=mapper)
    finally:
        store.remove()
    loaded = load_scenario(out)
    if stats is not None:
        stats.update(trace_stats)
        stats.update(_summary(loaded, store.num_rows))
    return loaded.root


def _empty_paths() -> pd.DataFrame:
    from rflscm.sim.backend import empty_path_table
    from rflscm.sim.stream import PATH_TABLE_COLUMNS

    table = empty_path_table().drop(columns="rx_index")
    table = table.assign(
        site_id=pd.Series(dtype="int32"),
        freq_hz=pd.Series(dtype="float64"),
        grid_id=pd.Series(dtype="int64"),
        point_id=pd.Series(dtype="int16"),
    )
    return table[PATH_TABLE_COLUMNS]


def write_measurements(
    scenario: Scenario,
    paths: pd.DataFrame | PathStore,
    config: SimulationConfig,
    rng: np.random.Generator,
    out: Path,
    paths_written: bool = False,
    mapper: Mapper = map,
) -> None:
    """The measurement step of :func:`build_scenario` (also run alone on an existing trace, see
    :func:`rflscm.sim.remeasure.remeasure`): truth/ and the measurements of ``config``'s regime, saved
    with the scenario into ``out``.  ``rng`` draws the report error exactly as the ideal regime did; the
    field effects draw from a generator of their own (seeded by ``config.seed``).

    ``paths``: the whole path table, or a :class:`~rflscm.sim.stream.PathStore` read one (site, carrier) at
    a time.  Both regimes stream: the ideal one per (round, cell) (:func:`rflscm.sim.stream.stream_ideal`), the
    field one per round and cell (:func:`rflscm.sim.field_stream.stream_field`).  ``paths_written``:
    ``truth/paths.parquet`` exists already (the trace appended it).  ``mapper``: where the ideal regime's noiseless
    RSRP is computed, one (site, carrier, round) per job (the field regime runs in-process)."""
    from rflscm.sim.stream import MemoryPaths, stream_ideal

    store = paths if isinstance(paths, PathStore) else MemoryPaths(paths)
    floor = None if config.truth_rsrp_margin_db is None else config.threshold_dbm - config.truth_rsrp_margin_db
    if config.measurements != "field":
        detect_on = None if config.detect_on == "any" else config.detect_on
        if not paths_written:
            _write_paths(out / "truth", store)
        streamed = out / ".measurements.parquet"  # appended block by block, never a whole table in memory
        stream_ideal(
            scenario,
            store,
            config.points_per_grid,
            config.measurement_model,
            rng,
            detect_on,
            out / "truth",
            floor,
            config.angle_grid,
            measurements_file=streamed,
            mapper=mapper,
        )
        save_scenario(scenario, out, table_format="parquet")  # meta names measurements.parquet: written empty
        os.replace(streamed, out / str(scenario.meta.measurements))
        return
    from rflscm.sim.field_stream import stream_field

    if not paths_written:
        _write_paths(out / "truth", store)
    meta = dataclasses.replace(scenario.meta, reporting=config.field_model.reporting())
    scenario = dataclasses.replace(scenario, meta=meta)
    streamed = out / ".measurements.parquet"
    stream_field(
        scenario,
        store,
        config.points_per_grid,
        config.field_model,
        np.random.default_rng([config.seed, 12]),
        rng,
        out / "truth",
        floor,
        config.angle_grid,
        streamed,
    )
    save_scenario(scenario, out, table_format="parquet")
    os.replace(streamed, out / str(scenario.meta.measurements))


def _write_paths(folder: Path, store: PathStore) -> None:
    """``truth/paths.parquet`` of a store, one (site, carrier) at a time."""
    from rflscm.sim.stream import MemoryPaths, ParquetAppender, compact_paths

    folder.mkdir(parents=True, exist_ok=True)
    if isinstance(store, MemoryPaths):  # the table as it is, in its order
        compact_paths(store.paths).to_parquet(folder / PATHS_FILE, index=False, compression="zstd")
        return
    with ParquetAppender(folder / PATHS_FILE, compact_paths(_empty_paths())) as out:
        for key in store.group_keys():
            group = store.group(key)
            if group is not None:
                out.append(compact_paths(group))


def _summary(scenario: Scenario, num_paths: int) -> dict[str, float]:
    m = scenario.measurements
    return {
        "num_cells": float(len(scenario.cells[1])),
        "num_grids": float(len(scenario.grids)),
        "num_paths": float(num_paths),
        "measurement_rows": float(len(m)),
        "fraction_missing": float(m["rsrp_dbm"].isna().mean()) if len(m) else float("nan"),
        "reported_pairs_round1": float(len(m[m["round"] == 1].groupby(["cell_id", "grid_id"]))),
    }


def _normalised(scenario: Scenario) -> Scenario:
    """Cells tables in the loader's normal form (sorted, 0…n−1 index), so accessors work in memory."""
    cells = {r: t.sort_values("cell_id", ignore_index=True) for r, t in scenario.cells.items()}
    return dataclasses.replace(scenario, cells=cells)


def _crop(scan: PointCloud, config: SimulationConfig, sites: np.ndarray, grids: pd.DataFrame) -> PointCloud:
    """The scan inside the box around sites and grids grown by ``point_cloud_margin_m``."""
    corners = np.vstack([sites[:, :2], grids[["x", "y"]].to_numpy()])
    lo, hi = corners.min(axis=0) - config.point_cloud_margin_m, corners.max(axis=0) + config.point_cloud_margin_m
    keep = ((scan.xyz[:, :2] >= lo) & (scan.xyz[:, :2] <= hi)).all(axis=1)
    return PointCloud(scan.xyz[keep], scan.classification[keep])


def _provenance(backend, config: SimulationConfig, scene, changes) -> dict[str, Any]:
    from rflscm import __version__

    grid = config.angle_grid
    return {
        "generator": f"rflscm {__version__} simulate",
        "backend": _BACKEND_KINDS.get(type(backend).__name__, type(backend).__name__),
        "scene": scene or backend.name,
        "seed": config.seed,
        "angle_grid": grid.to_dict(),
        "measurements": config.measurements,
        "noise": {
            "sigma_db": config.noise_sigma_db,
            "quantization_db": config.quantization_db,
            "threshold_dbm": config.rsrp_threshold_dbm,
        },
        **({"field": to_dict(config.field_model)} if config.measurements == "field" else {}),
        "points_per_grid": config.points_per_grid,
        "round2_changes": changes,
        "config": _config_record(config),
    }


def _config_record(config: SimulationConfig) -> dict[str, Any]:
    """The config as ``scenario.yaml`` records it; ``trace_range_m`` only when set (a scenario simulated without a
    range keeps the very file it had before the key existed)."""
    record = to_dict(config)
    if record.get("trace_range_m") is None:
        record.pop("trace_range_m", None)
    return record
