"""CPU time of one procedural trace per receiver in the grown city (issue 29, docs/DECISIONS.md).

For each site count: the grown city of `simulate --sites N` (grown_scene_options), its most central roof as the
transmitter (3 m above it), ~250 random receivers in the central 300 m × 300 m (the outdoor ones), one trace at
3.5 GHz; prints buildings, receivers and CPU seconds (``time.process_time``, so load on a shared machine does not
inflate it).  Usage: ``python scripts/procedural_trace_cost.py 7 37 167``.
"""

from __future__ import annotations

import sys
import time

import numpy as np

from rflscm.sim.procedural import ProceduralCity, grown_scene_options


def main(counts: list[int]) -> None:
    for n in counts:
        city = ProceduralCity(seed=0, **grown_scene_options("city", n, 7))
        rng = np.random.default_rng(0)
        rx = np.column_stack([rng.uniform(-150, 150, (250, 2)), np.full(250, 1.5)])
        rx = rx[city.is_outdoor(rx[:, :2])]
        roofs = city.rooftops()
        tx = roofs[np.argmin(np.hypot(roofs[:, 0], roofs[:, 1]))] + np.array([0.0, 0.0, 3.0])
        start = time.process_time()
        city.trace(tx, rx, 3.5e9)
        cpu = time.process_time() - start
        print(
            f"{n} sites: {city.num_buildings} buildings, {len(rx)} rx: {cpu:.2f} CPU s per trace, "
            f"{1000 * cpu / len(rx):.1f} CPU ms per rx",
            flush=True,
        )


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or [7, 37, 167])
