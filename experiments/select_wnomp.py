"""WNOMP's settings chosen on held-aside round-1 beams for a whole scenario, as `rflscm demo` chooses them, printed as
the `--set` options that give them to `rflscm train --model wnomp` and to RF-LSCM's fallback (issue 28).

Usage (from the repository root):

    PYTHONPATH=src python experiments/select_wnomp.py SCENARIO OUT.csv

Writes every candidate's held-aside MAE to OUT.csv (the demo's `wnomp_selection.csv`) and prints two lines: the
`--set` options for `train --model wnomp`, then those for `train --model rflscm` (`corrections.wnomp_fallback.*`).
"""

from __future__ import annotations

import sys

from rflscm.data import load_scenario
from rflscm.data.io import write_table
from rflscm.geometry import AngleGrid
from rflscm.models.wnomp_select import select_wnomp


def main(scenario: str, out: str) -> None:
    chosen, table = select_wnomp(load_scenario(scenario), AngleGrid(), seed=0)
    write_table(table, out)
    keys = {"k_max": chosen.k_max, "weighting": chosen.weighting, "tolerance": chosen.tolerance}
    keys["residual_floor"] = chosen.residual_floor
    print(" ".join(f"--set {k}={v}" for k, v in keys.items()))
    print(" ".join(f"--set corrections.wnomp_fallback.{k}={v}" for k, v in keys.items()))


if __name__ == "__main__":
    main(*sys.argv[1:3])
