"""Helpers of the network tests: the tiny scenario with a pencil-beam SSB codebook and synthetic APS caches."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import torch
import yaml

from rflscm.data import load_scenario, read_table, write_table
from rflscm.data.examples import tiny_scenario
from rflscm.eval.cache import ScenarioAPS
from rflscm.geometry import AngleGrid

GRID = AngleGrid()  # 91 × 72: −12° elevation and 30° azimuth are bin centres


def pencil_scenario(root: Path) -> Path:
    """The tiny scenario (cells 11 @ 3.5 GHz, az 60°, and 12 @ 2.1 GHz) where cell 11 uses a single
    boresight SSB beam of the full 8 × 4 array and no electrical tilt, so its gain peaks where its
    mechanical boresight points."""
    tiny_scenario(root, seed=1)
    meta = yaml.safe_load((root / "scenario.yaml").read_text())
    meta["codebooks"]["pencil"] = {
        "type": "ssb",
        "azimuths_deg": [0.0],
        "tilts_deg": [0.0],
        "active_h": 8,
        "active_v": 4,
    }
    (root / "scenario.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    for name in ("cells_round1.csv", "cells_round2.csv"):
        cells = read_table(root / name)
        cells.loc[cells["cell_id"] == 11, ["ssb_codebook", "elec_tilt_deg"]] = [
            "pencil",
            0.0,
        ]
        write_table(cells, root / name)
    m = read_table(root / "measurements.csv")  # the pencil codebook has one beam
    drop = (m["cell_id"] == 11) & (m["beam_type"] == "ssb") & (m["beam_id"] > 0)
    write_table(m[~drop.to_numpy()].reset_index(drop=True), root / "measurements.csv")
    return root


def single_bin_cache(scenario, el_deg: float, az_ccw_east_deg: float, power: float) -> ScenarioAPS:
    """An APS cache where every (cell, grid) pair has one path of gain ``power`` at one direction."""
    el, az = GRID.bin_angles()
    n = int(np.argmin(np.abs(np.rad2deg(el) - el_deg) + np.abs(np.rad2deg(az) - az_ccw_east_deg)))
    assert abs(np.rad2deg(el[n]) - el_deg) < 1e-6 and abs(np.rad2deg(az[n]) - az_ccw_east_deg) < 1e-6
    cells, grids = scenario.cell_ids(), scenario.grid_ids()
    aps = [torch.full((len(grids), 1), power) for _ in cells]
    known = np.ones((len(cells), len(grids)), bool)
    return ScenarioAPS(cells, grids, [np.array([n]) for _ in cells], aps, known, GRID, "synthetic")


def load(root: Path):
    return load_scenario(root)


__all__ = ["GRID", "load", "pd", "pencil_scenario", "single_bin_cache"]
