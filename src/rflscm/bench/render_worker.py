"""The render bench's worker: load an RF-LSCM checkpoint and time ``model.aps`` on given pairs (a standalone script).

The render bench (:mod:`rflscm.bench.render_speed`) runs this file *by path* in a subprocess, once with
``PYTHONPATH`` at the current package's ``src`` and, with ``--baseline``, once at an older commit's exported
``src``, in turn, so it uses only what both have: ``rflscm.models.base.load_model`` and the model's ``aps``.
It is never imported as part of ``rflscm``.

For each pattern of the pairs file (``{name}_cells``, ``{name}_grids``, ``{name}_xyz``) the worker makes one
``model.aps`` call (after one small call that builds the stored ray samples, timed apart as ``setup_s``) and
records its wall and process CPU seconds (and of those the kernel's, with the minor page faults); it saves the APS of every pattern (``{name}`` in ``--aps-out``) and
prints one JSON line: the timings and the process's peak resident memory before and after the timed calls.

Usage: ``python render_worker.py --checkpoint CKPT --pairs PAIRS.npz --aps-out APS.pt [--threads N]``.
"""

from __future__ import annotations

import sys
from pathlib import Path

# run by path, Python puts this folder first on sys.path; drop it so that its modules cannot shadow others
_HERE = Path(__file__).resolve().parent
sys.path[:] = [p for p in sys.path if (Path(p).resolve() if p else Path.cwd().resolve()) != _HERE]

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402


def _peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _decoder_evals(model: Any) -> dict[str, int]:
    """Decoder evaluations so far per rendering stage (``coarse``, ``fine``)."""
    return {name: int(getattr(stage, "decoder_evals", 0)) for name, stage in getattr(model, "stages", {}).items()}


def _profile(model: Any, pairs: Any, name: str, top: int = 30) -> list[dict[str, Any]]:
    """cProfile of one ``model.aps`` call: the ``top`` functions by cumulative time (file:line(function))."""
    import cProfile
    import pstats

    prof = cProfile.Profile()
    prof.enable()
    model.aps(pairs[f"{name}_cells"], pairs[f"{name}_grids"], pairs[f"{name}_xyz"])
    prof.disable()
    stats = pstats.Stats(prof).stats  # type: ignore[attr-defined]
    rows: list[dict[str, Any]] = []
    for (path, line, func), (_, calls, self_s, cum_s, _) in stats.items():
        parts = Path(path).parts
        where = "/".join(parts[parts.index("rflscm") + 1 :]) if "rflscm" in parts else Path(path).name
        rows.append({"function": f"{where}:{line}({func})", "calls": calls, "self_s": self_s, "cum_s": cum_s})
    rows.sort(key=lambda r: -float(r["cum_s"]))
    return rows[:top]


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", required=True)
    p.add_argument("--pairs", required=True, help=".npz with {name}_cells, {name}_grids, {name}_xyz per pattern")
    p.add_argument("--aps-out", required=True, help="where to save the APS of every pattern (torch.save of a dict)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--profile", action="store_true", help="also profile (cProfile) one more call on the first pattern")
    args = p.parse_args(argv)

    import numpy as np
    import torch

    torch.set_num_threads(args.threads)
    import rflscm
    from rflscm.models.base import load_model

    t0 = time.perf_counter()
    model = load_model(args.checkpoint)
    load_s = time.perf_counter() - t0
    corrections = getattr(model, "corrections", None)
    if getattr(corrections, "rendered", None) is not None:  # the renderer is timed: not the pass's kept renders
        setattr(corrections, "rendered", None)  # noqa: B010 (older code's corrections have no such field)
    pairs = np.load(args.pairs)
    names = sorted({k.rsplit("_", 1)[0] for k in pairs.files})
    t0 = time.perf_counter()
    for name in names:  # the stored ray samples of every cell and kind are built on the first call
        model.aps(pairs[f"{name}_cells"][:8], pairs[f"{name}_grids"][:8], pairs[f"{name}_xyz"][:8])
    setup_s = time.perf_counter() - t0
    rss_setup = _peak_rss_mb()
    out: dict[str, object] = {
        "src": str(Path(rflscm.__file__).resolve().parents[1]),
        "threads": torch.get_num_threads(),
        "load_s": load_s,
        "setup_s": setup_s,
        "peak_rss_after_setup_mb": rss_setup,
    }
    aps = {}
    for name in names:
        cells, grids, xyz = pairs[f"{name}_cells"], pairs[f"{name}_grids"], pairs[f"{name}_xyz"]
        evals = _decoder_evals(model)
        before = resource.getrusage(resource.RUSAGE_SELF)
        wall, cpu = time.perf_counter(), time.process_time()
        x = model.aps(cells, grids, xyz)
        wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
        after = resource.getrusage(resource.RUSAGE_SELF)
        aps[name] = x.detach().cpu()
        out[name] = {
            "pairs": len(cells),
            "wall_s": wall,
            "cpu_s": cpu,
            "system_s": after.ru_stime - before.ru_stime,  # kernel time: page faults of fresh large tensors
            "minor_faults": after.ru_minflt - before.ru_minflt,
            "decoder_evals": {k: v - evals.get(k, 0) for k, v in _decoder_evals(model).items()},
        }
    out["peak_rss_mb"] = _peak_rss_mb()
    if args.profile:
        name = names[0]
        out["profile"] = {"pattern": name, "top": _profile(model, pairs, name)}
    torch.save(aps, args.aps_out)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
