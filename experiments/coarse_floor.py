"""MAE floor of HiTAM's coarse stage on the shipped scenario.

The true APS is summed per β × β block and sensed through the block-mean columns of A (what the
coarse stage renders and trains on), and through the paper's representative columns, beside the
fine-bin oracle.  Round 1, SSB and CSI-RS pooled.  HiTAM lost its representative mode in commit
908988d; the representative columns are picked here from ``AngleGrid.coarse(β).representative_bins()``,
as that mode did.

Usage: python experiments/coarse_floor.py [MAX_CELLS]   (about a minute for 12 cells on 2 cores)
"""

from __future__ import annotations

import sys

import numpy as np
import torch

from rflscm.data import BEAM_TYPES, load_scenario
from rflscm.geometry import AngleGrid
from rflscm.models.rflscm.hitam import HiTAM
from rflscm.sim import default_scenario_path
from rflscm.sim.truth import load_true_aps


def abs_errors_db(power_mw: torch.Tensor, measured_dbm: np.ndarray) -> np.ndarray:
    pred = 10.0 * np.log10(np.maximum(power_mw.numpy(), 1e-30))
    ok = np.isfinite(measured_dbm)
    return np.abs(pred - measured_dbm)[ok]


def main(max_cells: int) -> None:
    scen = load_scenario(default_scenario_path())
    grid = AngleGrid()
    truth = load_true_aps(scen, grid)
    cells = scen.cell_ids()[:max_cells]
    for beta in (2, 3):
        block, rep_bins = HiTAM(grid, beta, 16), grid.coarse(beta).representative_bins()
        errs: dict[str, list[np.ndarray]] = {"fine": [], "block": [], "representative": []}
        for beam_type in BEAM_TYPES:
            pairs, rsrp = scen.rsrp_table(1, beam_type)
            for cell in cells:
                rows = np.flatnonzero(pairs["cell_id"].to_numpy() == cell)
                a = scen.sensing(int(cell), beam_type, grid, round=1).double()  # [M, N] mW
                x = truth.aps(np.full(len(rows), cell), pairs["grid_id"].to_numpy()[rows], dtype=torch.float64)
                x_block = (x[:, block.children] * block.valid).sum(-1)  # [P, Nc]
                measured = rsrp[rows][:, : a.shape[0]]
                errs["fine"].append(abs_errors_db(x @ a.T, measured))
                errs["block"].append(abs_errors_db(x_block @ block.coarse_columns(a[None])[0].T, measured))
                errs["representative"].append(abs_errors_db(x_block @ a[:, rep_bins].T, measured))
        mae = {k: float(np.concatenate(v).mean()) for k, v in errs.items()}
        print(
            f"beta={beta}: fine oracle {mae['fine']:.2f} dB, coarse block-mean {mae['block']:.2f} dB, "
            f"representative {mae['representative']:.2f} dB  ({len(cells)} cells)"
        )


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 12)
