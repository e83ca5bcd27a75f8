"""From traced paths to ground truth: the true APS and the true RSRP (SPEC §6).

Both backends hand in the same path table (:mod:`rflscm.sim.backend`), traced
with isotropic antennas.  Here the paths of one (site, carrier) meet a grid and
an antenna:

* **true APS** of a (cell, grid): the path power gains binned on the
  :class:`~rflscm.geometry.AngleGrid` by angle of departure (world frame) and
  averaged over the grid's receiver points, x_n = (1/K) Σ_{k, p ∈ bin n} |a_{k,p}|²;
  co-sited cells on one carrier share it, since the antenna lives only in A;
* **true RSRP** of any antenna configuration, non-coherent over paths:
  r_m = (1/K) Σ_{k,p} P_t G_elem(ω_p) |w_mᴴ a(ω_p)|² |a_{k,p}|², computed with
  :func:`rflscm.antenna.sensing_matrix` on the paths' own directions, the very
  code that builds A.  Binning the paths first gives r ≈ A x, up to the
  discretisation of the directions (measured in the tests).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd
import torch

from rflscm.antenna import CellAntenna, Codebook, sensing_matrix
from rflscm.data import BEAM_TYPES
from rflscm.geometry import AngleGrid, unit_vectors

COMPACT_PATHS = {
    "site_id": "int32",
    "freq_hz": "float64",
    "grid_id": "int32",
    "point_id": "int16",
    "power_lin": "float32",
    "aod_el_rad": "float32",
    "aod_az_rad": "float32",
    "delay_s": "float32",
}
"""dtypes of ``truth/paths.parquet`` (float32 where it loses nothing that matters; ``interactions`` is
dictionary-encoded text)."""

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario

_CHUNK = 65_536  # paths per sensing-matrix evaluation
PATHS_FILE, APS_FILE, RSRP_FILE = "paths.parquet", "aps.parquet", "rsrp_noiseless.parquet"
"""File names inside ``truth/`` (see :mod:`rflscm.sim.truth`)."""


def path_directions(paths: pd.DataFrame, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """World-frame unit vectors ``[num_paths, 3]`` of the paths' angles of departure."""
    el = torch.tensor(paths["aod_el_rad"].to_numpy(dtype=np.float64))
    az = torch.tensor(paths["aod_az_rad"].to_numpy(dtype=np.float64))
    return unit_vectors(el, az).to(dtype)


def trim_paths(paths: pd.DataFrame, floor_db: float | None) -> pd.DataFrame:
    """Drop zero-power paths and paths more than ``floor_db`` below the strongest of their receiver.

    Groups by ``rx_index`` (a path table) or by (``grid_id``, ``point_id``) when present.
    """
    paths = paths[paths["power_lin"].to_numpy() > 0]
    if floor_db is None or len(paths) == 0:
        return paths.reset_index(drop=True)
    keys = ["grid_id", "point_id"] if "point_id" in paths.columns else ["rx_index"]
    strongest = paths.groupby(keys, sort=False)["power_lin"].transform("max").to_numpy()
    keep = paths["power_lin"].to_numpy() >= strongest * 10.0 ** (-floor_db / 10.0)
    return paths[keep].reset_index(drop=True)


def bin_paths(paths: pd.DataFrame, angle_grid: AngleGrid, points_per_grid: pd.Series | int) -> pd.DataFrame:
    """True APS of one (site, carrier): path power binned by AoD, averaged over each grid's points.

    Args:
        paths: rows with ``grid_id``, ``power_lin``, ``aod_el_rad``, ``aod_az_rad``.
        angle_grid: the bins.
        points_per_grid: receiver points K per grid (a Series indexed by ``grid_id``, or one
            number for all), including points that received no path.

    Returns:
        ``grid_id`` (int64), ``bin`` (int32), ``power_lin`` (float64, linear path gain) for the
        nonzero bins, sorted by (grid_id, bin).
    """
    if len(paths) == 0:
        return pd.DataFrame(
            {
                "grid_id": pd.Series(dtype="int64"),
                "bin": pd.Series(dtype="int32"),
                "power_lin": pd.Series(dtype="float64"),
            }
        )
    bins = angle_grid.bin_of(paths["aod_el_rad"].to_numpy(), paths["aod_az_rad"].to_numpy())
    frame = pd.DataFrame(
        {
            "grid_id": paths["grid_id"].to_numpy(np.int64),
            "bin": bins.astype(np.int32),
            "power_lin": paths["power_lin"].to_numpy(np.float64),
        }
    )
    aps = frame.groupby(["grid_id", "bin"], sort=True, as_index=False)["power_lin"].sum()
    if isinstance(points_per_grid, pd.Series):
        count = points_per_grid.reindex(aps["grid_id"].to_numpy()).to_numpy(dtype=np.float64)
    else:
        count = float(points_per_grid)
    aps["power_lin"] = aps["power_lin"].to_numpy() / count
    return aps.astype({"grid_id": "int64", "bin": "int32", "power_lin": "float64"})


def path_rsrp_mw(
    paths: pd.DataFrame,
    antenna: CellAntenna,
    codebook: Codebook,
    wavelength_m: float,
    grid_ids: np.ndarray,
    points_per_grid: pd.Series | int,
) -> np.ndarray:
    """True RSRP ``[num_grids, num_beams]`` [mW] of ``antenna``/``codebook`` from one (site, carrier)'s paths.

    r[g, m] = (1/K_g) Σ_{paths of g} A_m(ω_p) |a_p|² with A from :func:`sensing_matrix` on the
    paths' own directions (no binning); grids without paths get 0.

    Args:
        paths: rows with ``grid_id``, ``power_lin``, ``aod_el_rad``, ``aod_az_rad``.
        grid_ids: the output rows' grid ids ``[num_grids]`` (sorted or not).
    """
    grid_ids = np.asarray(grid_ids, dtype=np.int64)
    out = torch.zeros(len(grid_ids), codebook.num_beams, dtype=torch.float64)
    if len(paths):
        order = np.argsort(grid_ids, kind="stable")
        pos = np.searchsorted(grid_ids[order], paths["grid_id"].to_numpy(np.int64))
        pos = np.clip(pos, 0, len(grid_ids) - 1)
        known = grid_ids[order][pos] == paths["grid_id"].to_numpy(np.int64)
        rows = torch.as_tensor(order[pos][known])
        sel = paths[known]
        power = torch.tensor(sel["power_lin"].to_numpy(np.float64))
        directions = path_directions(sel)
        for start in range(0, len(sel), _CHUNK):
            end = start + _CHUNK
            a = sensing_matrix(antenna, codebook, directions[start:end], wavelength_m, dtype=torch.float64)
            out.index_add_(0, rows[start:end], (a * power[start:end]).T)  # [paths, beams]
    if isinstance(points_per_grid, pd.Series):
        count = points_per_grid.reindex(grid_ids).to_numpy(dtype=np.float64)
    else:
        count = np.full(len(grid_ids), float(points_per_grid))
    return out.numpy() / count[:, None]


def aps_rsrp_mw(
    aps: pd.DataFrame,
    antenna: CellAntenna,
    codebook: Codebook,
    wavelength_m: float,
    angle_grid: AngleGrid,
    grid_ids: np.ndarray,
) -> np.ndarray:
    """RSRP ``[num_grids, num_beams]`` [mW] as the models see it: r = A x with x the binned APS
    (``grid_id``, ``bin``, ``power_lin`` rows) and A on the grid's bin centres."""
    grid_ids = np.asarray(grid_ids, dtype=np.int64)
    a = sensing_matrix(antenna, codebook, angle_grid, wavelength_m, dtype=torch.float64)  # [beams, bins]
    out = np.zeros((len(grid_ids), codebook.num_beams))
    order = np.argsort(grid_ids, kind="stable")
    g = aps["grid_id"].to_numpy(np.int64)
    pos = np.clip(np.searchsorted(grid_ids[order], g), 0, len(grid_ids) - 1)
    known = grid_ids[order][pos] == g
    contrib = a.numpy()[:, aps["bin"].to_numpy()[known]] * aps["power_lin"].to_numpy()[known]  # [beams, rows]
    np.add.at(out, order[pos][known], contrib.T)
    return out


def to_dbm(power_mw: np.ndarray) -> np.ndarray:
    """mW → dBm; zero power becomes −inf (never reported)."""
    with np.errstate(divide="ignore"):
        return 10.0 * np.log10(power_mw)


def site_groups(paths: pd.DataFrame) -> dict[tuple[int, float], pd.DataFrame]:
    """Paths split by (``site_id``, ``freq_hz``): the trace each co-sited cell on a carrier shares."""
    return {(int(s), float(f)): g for (s, f), g in paths.groupby(["site_id", "freq_hz"], sort=True)}


def cell_rsrp_dbm(
    scenario: Scenario,
    cell_id: int,
    beam_type: str,
    round: int,
    paths: pd.DataFrame,
    grid_ids: np.ndarray,
    points_per_grid: np.ndarray | int,
) -> np.ndarray:
    """Noiseless RSRP [dBm] ``[grids, beams]`` of ``cell_id``'s ``beam_type`` beams in ``round`` from its site's
    ``paths`` at ``grid_ids`` (:func:`path_rsrp_mw` through the round's antenna and codebook)."""
    antenna, codebook = scenario.antenna(cell_id, round), scenario.codebook(cell_id, beam_type, round)
    return to_dbm(path_rsrp_mw(paths, antenna, codebook, scenario.wavelength_m(cell_id), grid_ids, points_per_grid))


def noiseless_rsrp(scenario: Scenario, paths: pd.DataFrame, points_per_grid: pd.Series | int) -> pd.DataFrame:
    """True RSRP of every (round, cell, grid, beam) before noise, quantisation and threshold.

    Args:
        scenario: a :class:`rflscm.data.Scenario` (cells of every round, grids, codebooks).
        paths: the truth paths (``site_id``, ``freq_hz``, ``grid_id``, ``power_lin``, AoD angles).
        points_per_grid: receiver points per grid (see :func:`bin_paths`).

    Returns:
        Long form ``round``, ``cell_id``, ``grid_id``, ``beam_type``, ``beam_id``, ``rsrp_dbm``
        (−inf where no path arrives), sorted by that key.  A cell whose round-r row equals its
        round-1 row reuses the round-1 values, so unchanged cells are bit-identical across rounds.
    """
    grid_ids = scenario.grid_ids()
    groups = site_groups(paths)
    empty = paths.iloc[:0]
    done: dict[tuple[int, str], np.ndarray] = {}
    frames = []
    for rnd in scenario.rounds():
        for cell_id in scenario.cell_ids():
            row = scenario.cell_row(cell_id, rnd)
            unchanged = rnd != 1 and row.equals(scenario.cell_row(cell_id, 1))
            sub = groups.get((int(row["site_id"]), float(row["freq_hz"])), empty)
            for beam_type in BEAM_TYPES:
                if not unchanged:
                    done[(int(cell_id), beam_type)] = cell_rsrp_dbm(
                        scenario, int(cell_id), beam_type, rnd, sub, grid_ids, points_per_grid
                    )
                frames.append(_long(done[(int(cell_id), beam_type)], rnd, int(cell_id), grid_ids, beam_type))
    return pd.concat(frames, ignore_index=True)


def _long(rsrp_dbm: np.ndarray, rnd: int, cell_id: int, grid_ids: np.ndarray, beam_type: str) -> pd.DataFrame:
    """``[num_grids, num_beams]`` → long-form rows of one (round, cell, beam type)."""
    num_grids, num_beams = rsrp_dbm.shape
    return pd.DataFrame(
        {
            "round": np.full(num_grids * num_beams, rnd, dtype=np.int64),
            "cell_id": np.full(num_grids * num_beams, cell_id, dtype=np.int64),
            "grid_id": np.repeat(grid_ids, num_beams),
            "beam_type": beam_type,
            "beam_id": np.tile(np.arange(num_beams, dtype=np.int64), num_grids),
            "rsrp_dbm": rsrp_dbm.reshape(-1),
        }
    )


def write_truth(
    folder: Path,
    scenario: Scenario,
    paths: pd.DataFrame,
    noiseless: pd.DataFrame,
    points_per_grid: pd.Series,
    angle_grid: AngleGrid,
    rsrp_floor_dbm: float | None = None,
) -> None:
    """Write ``truth/``: the paths, the true APS of every (cell, grid) on ``angle_grid``, and the
    noiseless RSRP rounded to 0.01 dB — without the (round, cell, grid) pairs whose strongest beam
    is below ``rsrp_floor_dbm`` (they can never be reported).  float32 where it loses nothing that
    matters, zstd-compressed Parquet."""
    folder.mkdir(parents=True, exist_ok=True)
    compact = paths.astype({**COMPACT_PATHS, "interactions": "category"})
    compact.to_parquet(folder / PATHS_FILE, index=False, compression="zstd")
    aps = true_aps_table(paths, scenario.cells[1], angle_grid, points_per_grid)
    aps.to_parquet(folder / APS_FILE, index=False, compression="zstd")
    if rsrp_floor_dbm is not None:
        best = noiseless.groupby(["round", "cell_id", "grid_id"], sort=False)["rsrp_dbm"].transform("max")
        noiseless = noiseless[(best >= rsrp_floor_dbm).to_numpy()]
    rsrp = noiseless.assign(rsrp_dbm=np.round(noiseless["rsrp_dbm"].to_numpy(), 2))
    rsrp = rsrp.astype(
        {
            "round": "int8",
            "cell_id": "int32",
            "grid_id": "int32",
            "beam_type": "category",
            "beam_id": "int16",
            "rsrp_dbm": "float32",
        }
    )
    rsrp.to_parquet(folder / RSRP_FILE, index=False, compression="zstd")


def true_aps_table(
    paths: pd.DataFrame, cells: pd.DataFrame, angle_grid: AngleGrid, points_per_grid: pd.Series | int
) -> pd.DataFrame:
    """True APS ``cell_id``, ``grid_id``, ``bin``, ``power_lin`` of every cell: its (site, carrier)'s
    paths binned once and shared by the co-sited cells on that carrier (world-frame APS)."""
    groups = site_groups(paths)
    frames = []
    for (site, freq), cell_ids in cells.groupby(["site_id", "freq_hz"], sort=True)["cell_id"]:
        sub = groups.get((int(site), float(freq)))
        if sub is None:
            continue
        aps = bin_paths(sub, angle_grid, points_per_grid)
        for cell_id in np.sort(cell_ids.to_numpy()):
            frames.append(aps.assign(cell_id=np.int32(cell_id)))
    if not frames:
        return pd.DataFrame(
            {
                "cell_id": pd.Series(dtype="int32"),
                "grid_id": pd.Series(dtype="int32"),
                "bin": pd.Series(dtype="int32"),
                "power_lin": pd.Series(dtype="float64"),
            }
        )
    out = pd.concat(frames, ignore_index=True)[["cell_id", "grid_id", "bin", "power_lin"]]
    out = out.astype({"cell_id": "int32", "grid_id": "int32"})
    return out.sort_values(["cell_id", "grid_id", "bin"], ignore_index=True)
