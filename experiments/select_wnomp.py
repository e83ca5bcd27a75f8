"""WNOMP's settings chosen on held-aside round-1 beams for a whole scenario, as `rflscm demo` chooses them, printed as
the `--set` options that give them to `rflscm train --model wnomp` and to RF-LSCM's fallback (issue 28).

Usage (from the repository root):

    PYTHONPATH=src python experiments/select_wnomp.py SCENARIO OUT.csv

Writes every candidate's held-aside MAE to OUT.csv (the demo's `wnomp_selection.csv`) and prints three lines: the
`--set` options for `train --model wnomp`, those for `train --model rflscm` (`corrections.wnomp_fallback.*`), and
the selection's wall time (the scenario's loading excluded; BENCHMARKS, "The demo on larger cities").
"""

from __future__ import annotations

import sys
import time

from rflscm.data import load_scenario
from rflscm.data.io import write_table
from rflscm.geometry import AngleGrid
from rflscm.models.wnomp_select import select_wnomp


def main(scenario: str, out: str) -> None:
    scen = load_scenario(scenario)
    begun = time.perf_counter()
    chosen, table = select_wnomp(scen, AngleGrid(), seed=0)
    seconds = time.perf_counter() - begun
    write_table(table, out)
    keys = {"k_max": chosen.k_max, "weighting": chosen.weighting, "tolerance": chosen.tolerance}
    keys["residual_floor"] = chosen.residual_floor
    print(" ".join(f"--set {k}={v}" for k, v in keys.items()))
    print(" ".join(f"--set corrections.wnomp_fallback.{k}={v}" for k, v in keys.items()))
    print(f"selection: {seconds:.1f} s, {int(table['beams'].iloc[0])} held-aside beams")


if __name__ == "__main__":
    main(*sys.argv[1:3])
