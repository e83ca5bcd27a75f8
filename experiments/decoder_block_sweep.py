"""How many (query, sample) pairs the decoder should evaluate at a time at inference (``fields.DECODER_BLOCK``).

Loads an RF-LSCM checkpoint (e.g. the render bench's ``<out>/render_model.ckpt``) and its pairs file
(``<out>/render_pairs.npz``), then renders the ``by_cell`` pattern with each block size in turn (``0`` = all
pairs at once, the training path's layout), ``--rounds`` times round-robin, and prints per block size the median
process CPU seconds, kernel seconds and minor page faults of one ``model.aps`` call, and whether the APS equal
the first block size's to the bit.

Usage: python experiments/decoder_block_sweep.py CKPT PAIRS.npz [--blocks 0,2048,4096,8192,32768] [--rounds 3]
(with ``PYTHONPATH`` at the ``src`` to measure; one thread).
"""

from __future__ import annotations

import argparse
import resource
import statistics
import time

import numpy as np
import torch


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("checkpoint")
    p.add_argument("pairs")
    p.add_argument("--blocks", default="0,2048,4096,8192,32768")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--pattern", default="by_cell")
    args = p.parse_args()
    torch.set_num_threads(1)
    import rflscm.models.rflscm.fields as fields_module
    from rflscm.models.base import load_model

    model = load_model(args.checkpoint)
    pairs = np.load(args.pairs)
    cells, grids, xyz = (pairs[f"{args.pattern}_{k}"] for k in ("cells", "grids", "xyz"))
    model.aps(cells[:8], grids[:8], xyz[:8])  # stored ray samples
    blocks = [int(b) for b in args.blocks.split(",")]
    rows: dict[int, list[tuple[float, float, int]]] = {b: [] for b in blocks}
    first: torch.Tensor | None = None
    same: dict[int, bool] = {}
    for _ in range(args.rounds):
        for block in blocks:
            fields_module.DECODER_BLOCK = block if block > 0 else 1 << 62  # type: ignore[attr-defined]
            before = resource.getrusage(resource.RUSAGE_SELF)
            cpu = time.process_time()
            out = model.aps(cells, grids, xyz)
            cpu = time.process_time() - cpu
            after = resource.getrusage(resource.RUSAGE_SELF)
            rows[block].append((cpu, after.ru_stime - before.ru_stime, after.ru_minflt - before.ru_minflt))
            first = out if first is None else first
            same[block] = same.get(block, True) and bool(torch.equal(out, first))
    print(f"{len(cells)} pairs ({args.pattern}); medians of {args.rounds} rounds")
    print("block      cpu_s   pairs/cpu_s   system_s   minor_faults   equal")
    for block in blocks:
        cpu = statistics.median(r[0] for r in rows[block])
        sys_s = statistics.median(r[1] for r in rows[block])
        faults = statistics.median(r[2] for r in rows[block])
        label = "all" if block == 0 else str(block)
        print(f"{label:>6} {cpu:9.2f} {len(cells) / cpu:12.1f} {sys_s:10.2f} {faults:14.0f}   {same[block]}")


if __name__ == "__main__":
    main()
