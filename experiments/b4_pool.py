"""Pool B4 runs over disjoint seeds: every draw's paired prior gain, their mean, std and how many are positive.

    python experiments/b4_pool.py RUN1/b4.json [RUN2/b4.json …]

Each file is ``rflscm bench b4 … --seed S --seeds N`` output (seed ``s`` draws the training grids and
initialises both arms).  Prints per draw the prior gain (prior off − prior on, measured MAE over all cells
[dB]), its mean, sample std and count of positive draws, then each arm's measured and truth MAE
(``truth_mae_db``), unseen-grid bias and training time, averaged over the draws.
Used for BENCHMARKS.md ("B4 over ten draws of the training grids").
"""

import json
import sys
from pathlib import Path

import numpy as np


def main(paths: list[str]) -> None:
    seeds: list[int] = []
    gains: list[tuple[float, float]] = []
    arms: dict[str, list[dict]] = {"prior_on": [], "prior_off": []}
    for path in paths:
        res = json.loads(Path(path).read_text())["results"]
        if set(res["seeds"]) & set(seeds):
            sys.exit(f"{path}: seeds {res['seeds']} overlap earlier files' {seeds}")
        seeds += res["seeds"]
        gains += [(g["ssb"], g["csi"]) for g in res["prior_gain_per_seed_db"]]
        for arm in arms:  # each file's means, weighted by its seeds below
            arms[arm] += [res["variants"][arm]] * len(res["seeds"])
    g = np.array(gains)
    for seed, (ssb, csi) in zip(seeds, g, strict=True):
        print(f"draw {seed}: prior gain SSB {ssb:+.2f}, CSI-RS {csi:+.2f} dB")
    print(f"{len(g)} draws: mean {g[:, 0].mean():+.2f} / {g[:, 1].mean():+.2f} dB, std {g[:, 0].std(ddof=1):.2f} / "
          f"{g[:, 1].std(ddof=1):.2f}, positive {int((g[:, 0] > 0).sum())} / {int((g[:, 1] > 0).sum())} of {len(g)}")  # fmt: skip
    for arm, runs in arms.items():
        for key in ("mae_db", "truth_mae_db"):
            ssb = np.mean([r[key]["ssb"]["all"] for r in runs])
            csi = np.mean([r[key]["csi"]["all"] for r in runs])
            print(f"{arm} {key}: SSB {ssb:.2f}, CSI-RS {csi:.2f} (all cells, mean over draws)")
        bias = [r["unseen_bias_db"] for r in runs]
        print(
            f"{arm} unseen bias: SSB {np.mean([b['ssb'] for b in bias]):+.2f}, CSI-RS {np.mean([b['csi'] for b in bias]):+.2f}"
        )
        print(f"{arm} train time: {np.mean([r['train_time_s'] for r in runs]):.0f} s")


if __name__ == "__main__":
    main(sys.argv[1:])
