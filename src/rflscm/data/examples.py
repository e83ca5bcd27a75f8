"""A tiny scenario folder for tests and examples.

:func:`tiny_scenario` writes, as a user would (a hand-written YAML, CSV or
Parquet tables, a PLY point cloud):

* 2 co-sited cells, ids 11 (3.5 GHz, azimuth 60°) and 12 (2.1 GHz, azimuth 180°),
  25 m up at the origin; optional cell columns left out, so defaults apply;
* round 2 where cell 12 is tilted 6° further down (mechanical tilt 2° → 8°);
* 3 grids, ids 100…102, 1.5 m high, 80…100 m from the site;
* SSB codebook ``ssb8`` (8 beams) and CSI codebook ``csi8`` (8 DFT beams);
* measurements for both rounds and beam types: free-space line-of-sight RSRP through
  the cell's real sensing matrix, 2 dB log-normal noise, 1 dB quantisation, and NaN
  below −120 dBm or randomly not reported (≈15 %, at least one);
* a 3-point point cloud (one ground point, two building points).

Ids are deliberately not 0…n−1, so code that confuses ids with positions fails.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from rflscm.data.io import write_table
from rflscm.data.loader import load_scenario
from rflscm.data.measurements import BEAM_TYPES
from rflscm.data.pointcloud import PointCloud, write_point_cloud
from rflscm.data.scenario import Scenario

_YAML = """\
name: tiny
description: two co-sited cells, three grids (rflscm.data.examples.tiny_scenario)
origin: null
rsrp_threshold_dbm: -120.0
frequencies_hz: [2.1e9, 3.5e9]
codebooks:
  ssb8: {{type: ssb}}
  csi8: {{type: dft, beams_h: [-3, -1, 1, 3], beams_v: [0, 2]}}
rounds:
  1: {{cells: cells_round1{ext}}}
  2: {{cells: cells_round2{ext}}}
grids: grids{ext}
point_cloud: point_cloud.ply
simulation: {{generator: rflscm.data.examples.tiny_scenario, seed: {seed}}}
"""

NOISE_DB = 2.0
MISSING_FRACTION = 0.15


def _cells(mech_tilt_cell12: float) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "cell_id": [11, 12],
            "site_id": [1, 1],
            "x": [0.0, 0.0],
            "y": [0.0, 0.0],
            "z": [25.0, 25.0],
            "azimuth_deg": [60.0, 180.0],
            "mech_tilt_deg": [4.0, mech_tilt_cell12],
            "elec_tilt_deg": [6.0, 4.0],
            "freq_hz": [3.5e9, 2.1e9],
            "ssb_codebook": ["ssb8", "ssb8"],
            "csi_codebook": ["csi8", "csi8"],
        }
    )


def _grids() -> pd.DataFrame:
    return pd.DataFrame(
        {"grid_id": [100, 101, 102], "x": [50.0, -40.0, 10.0], "y": [80.0, -90.0, -95.0], "z": [1.5, 1.5, 1.5]}
    )


def los_rsrp_dbm(scenario: Scenario, cell_id: int, grid_xyz: np.ndarray, beam_type: str, round: int) -> np.ndarray:
    """Noise-free free-space line-of-sight RSRP ``[num_beams]`` [dBm] of a cell at a point ``[3]`` [m].

    RSRP_m = A[m, ω_LOS] · (λ / 4πd)²  (Friis path gain, the sensing matrix of SPEC §2).
    """
    delta = np.asarray(grid_xyz, np.float64) - scenario.cell_position(cell_id)
    distance = float(np.linalg.norm(delta))
    direction = torch.as_tensor(delta / distance, dtype=torch.float64)[None, :]  # [1, 3]
    a = scenario.sensing(cell_id, beam_type, direction, round=round, dtype=torch.float64)[:, 0]  # [num_beams] mW
    gain = (scenario.wavelength_m(cell_id) / (4 * math.pi * distance)) ** 2
    return 10.0 * np.log10(a.numpy() * gain)


def _measurements(scenario: Scenario, seed: int) -> pd.DataFrame:
    rng = np.random.default_rng(seed)
    rows = []
    for rnd in scenario.rounds():
        for cell_id in scenario.cell_ids():
            for _, grid in scenario.grids.iterrows():  # 3 grids: clarity over speed
                for beam_type in BEAM_TYPES:
                    clean = los_rsrp_dbm(scenario, int(cell_id), grid[["x", "y", "z"]].to_numpy(), beam_type, rnd)
                    for beam_id, value in enumerate(clean):
                        rows.append((rnd, int(cell_id), int(grid["grid_id"]), beam_type, beam_id, value))
    table = pd.DataFrame(rows, columns=["round", "cell_id", "grid_id", "beam_type", "beam_id", "rsrp_dbm"])
    noisy = np.round(table["rsrp_dbm"].to_numpy() + rng.normal(0.0, NOISE_DB, len(table)))
    noisy = np.minimum(noisy, -31.0)
    missing = (noisy < scenario.meta.rsrp_threshold_dbm) | (rng.random(len(table)) < MISSING_FRACTION)
    missing[rng.integers(len(table))] = True  # at least one NaN
    table["rsrp_dbm"] = np.where(missing, np.nan, noisy)
    return table


def tiny_scenario(root: str | Path, seed: int = 0, table_format: str = "csv") -> Path:
    """Write the tiny scenario (module docstring) into folder ``root`` and return the folder.

    Args:
        root: target folder (created if needed).
        seed: seed of the measurement noise and missing beams.
        table_format: ``csv`` or ``parquet`` for every table.
    """
    ext = {"csv": ".csv", "parquet": ".parquet"}[table_format]
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    write_table(_cells(2.0), root / f"cells_round1{ext}")
    write_table(_cells(8.0), root / f"cells_round2{ext}")
    write_table(_grids(), root / f"grids{ext}")
    xyz = np.array([[0.0, 0.0, 0.0], [30.0, 30.0, 10.0], [-30.0, 20.0, 15.0]])
    write_point_cloud(PointCloud(xyz, np.array([2, 6, 6], dtype=np.uint8)), root / "point_cloud.ply")
    text = _YAML.format(ext=ext, seed=seed)
    (root / "scenario.yaml").write_text(text)  # first without measurements, to compute them
    measurements = _measurements(load_scenario(root), seed)
    write_table(measurements, root / f"measurements{ext}")
    (root / "scenario.yaml").write_text(text + f"measurements: measurements{ext}\n")
    return root
