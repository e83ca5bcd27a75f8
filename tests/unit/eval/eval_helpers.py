"""Helpers of the evaluation tests: a small simulated scenario and a scenario whose truth lies exactly on
angle-grid bins, built through the data API (a module of its own: ``conftest`` is not importable by name)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import torch
import yaml

from rflscm.data import load_scenario, read_table, write_table
from rflscm.data.examples import tiny_scenario
from rflscm.geometry import AngleGrid
from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario

GRID = AngleGrid(num_el=31, num_az=36, el_min_deg=-90.0, el_step_deg=6.0)


def simulate(out: Path, **overrides: object) -> Path:
    """A 2-site, 2-carrier procedural scenario with 60 grids on the 31 × 36 test grid."""
    config = SimulationConfig(
        num_sites=2,
        max_grids=60,
        seed=4,
        site_radius_m=120.0,
        angle_grid=GRID,
        point_cloud_points_per_m2=0.05,
        **overrides,
    )
    build_scenario(ProceduralCity(seed=3, size_m=240.0, num_buildings=12), config, out, progress=False)
    return out


def on_grid_truth_scenario(root: Path, noise_db: float, seed: int = 0) -> Path:
    """The tiny scenario (2 cells, 3 grids) re-measured from a known APS whose paths sit on bin centres of
    :data:`GRID`: RSRP = 10·log10(A x) exactly (``noise_db`` = 0, no quantisation) or with log-normal
    noise and 1 dB quantisation; ``truth/aps.parquet`` holds x, so the oracle sees the exact truth."""
    tiny_scenario(root, seed=seed)
    scenario = load_scenario(root)
    rng = np.random.default_rng(seed)
    front = np.flatnonzero(np.abs(GRID.bin_angles()[0]) < np.radians(30))
    truth = []
    for cell in scenario.cell_ids():
        for grid in scenario.grid_ids():
            bins = rng.choice(front, 2, replace=False)
            truth += [(int(cell), int(grid), int(b), float(p)) for b, p in zip(bins, 10 ** rng.uniform(-11, -9, 2))]
    aps = pd.DataFrame(truth, columns=["cell_id", "grid_id", "bin", "power_lin"])
    (root / "truth").mkdir()
    aps.to_parquet(root / "truth" / "aps.parquet", index=False)
    rows = []
    for rnd in scenario.rounds():
        for cell in scenario.cell_ids():
            x = np.zeros((len(scenario.grid_ids()), GRID.num_bins))
            sub = aps[aps["cell_id"] == cell]
            x[np.searchsorted(scenario.grid_ids(), sub["grid_id"]), sub["bin"]] = sub["power_lin"]
            for beam_type in ("ssb", "csi"):
                a = scenario.sensing(int(cell), beam_type, GRID, round=rnd, dtype=torch.float64).numpy()
                rsrp = 10 * np.log10(x @ a.T)  # [grids, beams]
                if noise_db > 0:
                    rsrp = np.round(rsrp + rng.normal(0.0, noise_db, rsrp.shape))
                rsrp[rsrp < scenario.meta.rsrp_threshold_dbm] = np.nan
                for g, grid in enumerate(scenario.grid_ids()):
                    rows += [(rnd, int(cell), int(grid), beam_type, b, rsrp[g, b]) for b in range(a.shape[0])]
    columns = ["round", "cell_id", "grid_id", "beam_type", "beam_id", "rsrp_dbm"]
    write_table(pd.DataFrame(rows, columns=columns), root / "measurements.csv")
    meta = yaml.safe_load((root / "scenario.yaml").read_text())
    meta["truth"] = "truth"
    meta["simulation"] = {
        "angle_grid": {
            "num_el": GRID.num_el,
            "num_az": GRID.num_az,
            "el_min_deg": GRID.el_min_deg,
            "el_step_deg": GRID.el_step_deg,
        },
        "points_per_grid": 1,
    }
    (root / "scenario.yaml").write_text(yaml.safe_dump(meta))
    assert read_table(root / "measurements.csv")["rsrp_dbm"].notna().mean() > 0.5
    return root
