"""Parts of a scenario: a cut of some cells at some grids (:func:`scenario_part`) and a tiling of a network into
parts of a few sites each (:func:`plan_tiles`).

A part keeps its cells' measurements at its grids, the cells it leaves out enter as interference: their reported
SSB at the part's grids (:attr:`Scenario.outside_ssb`, which the SS-SINR detection bounds of
:mod:`rflscm.data.reporting` count), and the point cloud is cropped to the box around the kept cells and grids
grown by a margin.  The benchmarks cut their sizes this way; a tiled model (``rflscm train --tile-sites``) cuts
its tiles this way.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from rflscm.data.measurements import reported_pairs
from rflscm.data.scenario import OUTSIDE_SSB_COLUMNS
from rflscm.errors import ConfigError, DataError

if TYPE_CHECKING:
    from rflscm.data.pointcloud import PointCloud
    from rflscm.data.scenario import Scenario

__all__ = ["Tile", "crop_cloud", "outside_ssb", "plan_tiles", "scenario_part", "tile_scenario"]


def scenario_part(
    full: Scenario, keep_cells: np.ndarray, grid_ids: np.ndarray | pd.Series, crop_margin_m: float | None
) -> Scenario:
    """The part of ``full`` made of the cells ``keep_cells`` (every round's table) at the grids ``grid_ids``.

    Measurements: the kept cells' rows at the kept grids, in ``full``'s order.  ``outside_ssb``: the reported SSB of
    every other cell at the kept grids (with ``full``'s own ``outside_ssb`` there, when ``full`` is itself a part).
    The point cloud is cropped to the box around the kept cells and grids grown by ``crop_margin_m`` [m] in x and y
    (None: not cropped).  Deterministic: the same arguments give an equal scenario.
    """
    keep_cells = np.asarray(keep_cells, dtype=np.int64)
    grids = full.grids[full.grids["grid_id"].isin(np.asarray(grid_ids)).to_numpy()].reset_index(drop=True)
    m = full.measurements
    m = m[m["cell_id"].isin(keep_cells).to_numpy() & m["grid_id"].isin(grids["grid_id"]).to_numpy()]
    cells = {r: t[t["cell_id"].isin(keep_cells)].reset_index(drop=True) for r, t in full.cells.items()}
    return dataclasses.replace(
        full,
        cells=cells,
        grids=grids,
        measurements=m.reset_index(drop=True),
        point_cloud=crop_cloud(full.point_cloud, cells[1], grids, crop_margin_m),
        outside_ssb=outside_ssb(full, keep_cells, grids["grid_id"]),
    )


def outside_ssb(full: Scenario, keep_cells: np.ndarray, grid_ids: np.ndarray | pd.Series) -> pd.DataFrame:
    """The reported SSB of the cells a part leaves out, at its grids (columns ``OUTSIDE_SSB_COLUMNS``): the
    interference that kept some of the part's SSB beams undetected (an SS-SINR rule's bound needs it;
    :mod:`rflscm.data.reporting`).  A ``full`` that is itself a part adds its own ``outside_ssb`` at those grids."""
    m = full.measurements
    rows = m[
        (m["beam_type"] == "ssb").to_numpy()
        & ~m["cell_id"].isin(keep_cells).to_numpy()
        & m["grid_id"].isin(grid_ids).to_numpy()
        & m["rsrp_dbm"].notna().to_numpy()
    ]
    freq = full.cells[1].set_index("cell_id")["freq_hz"]
    out = rows.assign(freq_hz=freq.loc[rows["cell_id"]].to_numpy())[list(OUTSIDE_SSB_COLUMNS)]
    inherited = full.outside_ssb
    if inherited is not None and len(inherited):
        out = pd.concat([out, inherited[inherited["grid_id"].isin(grid_ids).to_numpy()][list(OUTSIDE_SSB_COLUMNS)]])
    return out.reset_index(drop=True)


def crop_cloud(
    cloud: PointCloud | None, cells: pd.DataFrame, grids: pd.DataFrame, margin_m: float | None
) -> PointCloud | None:
    """The points of ``cloud`` inside the x/y box around ``cells`` and ``grids`` grown by ``margin_m`` [m] (every
    height kept: the ground and the roofs); ``cloud`` itself when it or ``margin_m`` is None."""
    if cloud is None or margin_m is None:
        return cloud
    pts = np.concatenate([cells[["x", "y", "z"]].to_numpy(np.float64), grids[["x", "y", "z"]].to_numpy(np.float64)])
    lo, hi = pts.min(0) - margin_m, pts.max(0) + margin_m
    lo[2], hi[2] = -np.inf, np.inf  # keep the ground and the roofs
    inside = np.all((cloud.xyz >= lo) & (cloud.xyz <= hi), axis=1)
    return type(cloud)(cloud.xyz[inside], cloud.classification[inside])


# --- tiles ---------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Tile:
    """One tile of a network: the sites it owns, their cells, and the grids where those cells have round-1 reports."""

    index: int
    sites: tuple[int, ...]
    cells: tuple[int, ...]
    """The cells the tile owns (every cell of its sites; each cell of the network is in exactly one tile)."""
    grids: tuple[int, ...]
    """Grids where the tile's cells have a reported round-1 RSRP (tiles overlap here: a grid heard by two tiles'
    cells is in both)."""
    pairs: int = 0
    """Training pairs of the tile: distinct (cell, grid) pairs of its cells with a reported round-1 RSRP (what a
    tile's training and its pass after training cost grows with; a tiled run shares its budget by it)."""


def plan_tiles(scenario: Scenario, tile_sites: int) -> list[Tile]:
    """Split ``scenario``'s sites into compact tiles of about ``tile_sites`` sites each (deterministic).

    The split is a k-d bisection of the sites' positions into ⌈sites / ``tile_sites``⌉ tiles, balanced by training
    pairs rather than by sites: a group of sites meant for t tiles is sorted along its longer extent (x or y; ties
    by site id) and cut where ⌊t/2⌋ of the tiles' share of its training pairs ends (each side keeping at least a
    site per tile), until a group is one tile.  A dense downtown thus gets tiles of fewer sites than the suburbs,
    and the tiles cost about the same to train (at 1 002 cells, cutting by sites gave tiles of 7 534 to 146 446
    pairs).  Sites weigh their training pairs plus one, so where no site has pairs the cut is by sites.  A tile whose
    cells have no reported round-1 RSRP (nothing to learn from) joins the tile of the nearest site (its cells must
    still be answered).  Grids: where a tile's cells have a round-1 report in ``scenario`` (give the training
    scenario).
    """
    if tile_sites < 1:
        raise ConfigError(f"a tile must hold at least one site (got tile_sites = {tile_sites}).")
    cells1 = scenario.cells[1]
    sites_xy = cells1.groupby("site_id")[["x", "y"]].mean().sort_index()
    site_ids = sites_xy.index.to_numpy(np.int64)
    xy = sites_xy.to_numpy(np.float64)
    grids_of = reported_pairs(scenario.measurements).groupby("cell_id")["grid_id"].unique()
    pairs_of = grids_of.map(len)
    site_of = cells1.drop_duplicates("cell_id").set_index("cell_id")["site_id"]
    site_pairs = pairs_of.groupby(site_of.reindex(pairs_of.index).to_numpy()).sum()
    weight = site_pairs.reindex(site_ids, fill_value=0).to_numpy(np.float64) + 1.0
    groups = _bisect(np.arange(len(site_ids)), xy, site_ids, weight, math.ceil(len(site_ids) / tile_sites))
    cells_of_site = cells1.groupby("site_id")["cell_id"].apply(lambda s: np.sort(s.to_numpy(np.int64)))
    members = [sorted(int(site_ids[i]) for i in g) for g in groups]
    heard = [any(c in grids_of.index for s in sites for c in cells_of_site[s]) for sites in members]
    if not any(heard):
        raise DataError(f"scenario {scenario.meta.name!r} has no reported round-1 RSRP: there is nothing to tile.")
    merged: list[list[int]] = [list(s) if h else [] for s, h in zip(members, heard, strict=True)]
    for sites, h in zip(members, heard, strict=True):
        if h:
            continue
        centre = xy[np.searchsorted(site_ids, sites)].mean(0)
        best = None
        for t, own in enumerate(merged):
            if not own or not heard[t]:
                continue
            d = float(np.linalg.norm(xy[np.searchsorted(site_ids, own)] - centre, axis=1).min())
            if best is None or d < best[0]:
                best = (d, t)
        assert best is not None
        merged[best[1]] = sorted(merged[best[1]] + sites)
    tiles: list[Tile] = []
    for sites in (s for s in merged if s):
        cells = np.concatenate([cells_of_site[s] for s in sites])
        have = [c for c in cells if c in grids_of.index]
        grids = np.unique(np.concatenate([grids_of[c] for c in have])) if have else np.empty(0, np.int64)
        pairs = int(sum(len(grids_of[c]) for c in have))
        tiles.append(
            Tile(len(tiles), tuple(sites), tuple(int(c) for c in np.sort(cells)), tuple(int(g) for g in grids), pairs)
        )
    return tiles


def _bisect(rows: np.ndarray, xy: np.ndarray, ids: np.ndarray, weight: np.ndarray, tiles: int) -> list[np.ndarray]:
    """``rows`` (indices into ``xy``, ``weight``) split into ``tiles`` spatially compact groups of near-equal
    weight, each of at least one row when there are enough."""
    if tiles <= 1 or len(rows) <= 1:
        return [rows]
    span = xy[rows].max(0) - xy[rows].min(0)
    axis = 0 if span[0] >= span[1] else 1
    order = rows[np.lexsort((ids[rows], xy[rows, axis]))]
    left = tiles // 2
    # the first k rows hold cum[k - 1] of the weight: cut nearest the left tiles' share, a row per tile each side
    cum = np.cumsum(weight[order])
    lo, hi = min(left, len(rows) - 1), max(len(rows) - (tiles - left), 1)
    ks = np.arange(lo, max(hi, lo) + 1)
    cut = int(ks[np.argmin(np.abs(cum[ks - 1] - cum[-1] * left / tiles))])
    return _bisect(order[:cut], xy, ids, weight, left) + _bisect(order[cut:], xy, ids, weight, tiles - left)


def tile_scenario(scenario: Scenario, tile: Tile, crop_margin_m: float | None) -> Scenario:
    """The part of ``scenario`` a tile trains on: its cells at its grids, the other cells' SSB there as
    interference, the point cloud cropped around it (:func:`scenario_part`)."""
    return scenario_part(scenario, np.asarray(tile.cells, np.int64), np.asarray(tile.grids, np.int64), crop_margin_m)
