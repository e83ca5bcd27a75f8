"""Peak memory of loading a scenario's measurements, phase by phase (issue 29, memory).

    python scripts/profile_load.py SCENARIO

Prints, for each phase of ``load_scenario``'s measurements path (read the file, validate the table), the
process's peak RSS so far (``ru_maxrss``) and the peak of the traced (numpy / Python) allocations in that phase
(``tracemalloc``; Arrow's own buffers are not traced, the RSS sees them), in bytes per measurement row.
"""

from __future__ import annotations

import resource
import sys
import time
import tracemalloc

from rflscm.data import load_scenario
from rflscm.data.loader import _read, load_meta, locate_scenario


def rss_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def main(path: str) -> None:
    root, yaml_path = locate_scenario(path)
    meta = load_meta(yaml_path)
    assert meta.measurements is not None
    base = rss_gb()
    tracemalloc.start()
    t0 = time.perf_counter()
    df, _ = _read(root, meta.measurements, "measurements", yaml_path.name, False)
    rows = len(df)
    _, peak = tracemalloc.get_traced_memory()
    print(f"rows {rows:,}; baseline RSS {base:.2f} GB")
    per = lambda b: b / rows  # noqa: E731
    print(
        f"read table: {time.perf_counter() - t0:.1f} s, traced peak {per(peak):.0f} B/row, RSS peak {rss_gb():.2f} GB"
    )
    held = df.memory_usage(deep=True).sum()
    print(f"  table as read: {per(held):.0f} B/row")
    del df
    tracemalloc.reset_peak()
    t0 = time.perf_counter()
    scenario = load_scenario(path)
    _, peak = tracemalloc.get_traced_memory()
    print(
        f"load_scenario: {time.perf_counter() - t0:.1f} s, traced peak {per(peak):.0f} B/row, RSS peak {rss_gb():.2f} GB"
    )
    m = scenario.measurements
    print(f"  measurements held: {per(m.memory_usage(deep=True).sum()):.0f} B/row; dtypes {dict(m.dtypes.astype(str))}")


if __name__ == "__main__":
    main(sys.argv[1])
