"""Probe B4 (point-cloud prior on/off, 10 % of the training grids): both arms with extra overrides.

    python experiments/b4_probe.py SCENARIO OUT [--extra JSON] [--effect STEP] [--seed N] [--seeds N]

Runs :func:`rflscm.bench.b04_point_cloud.run_b4` at the quick size on ``SCENARIO`` (one thread) and
writes ``OUT/b4.json`` and the plots; prints each arm's measured MAE, truth MAE and unseen-grid bias.
``--extra '{"loss": {"missing_penalty": 0}}'`` trains both arms without the missing-beam penalty, for
example; ``--seed`` picks the first draw of training grids (seed s draws them and initialises both arms);
``--effect reporting`` (any B8 step: ideal, reporting, noise, array_error, ue_sampling, all) first re-measures
``SCENARIO``'s trace with that field effect alone, into ``OUT/scenario``.  Used for docs/DECISIONS.md
("B4's field reversal was one draw of 15 grids").
"""

import argparse
import json
from pathlib import Path

import torch

from rflscm.bench import BenchContext
from rflscm.bench.b04_point_cloud import run_b4
from rflscm.bench.b08_realism import STEPS, measured
from rflscm.bench.harness import bench_size


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scenario")
    p.add_argument("out", type=Path)
    p.add_argument("--extra", default="{}", help="overrides for both arms, as JSON")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--effect", default=None, choices=list(STEPS), help="re-measure the trace with this B8 step first")
    p.add_argument("--seeds", type=int, default=1)
    args = p.parse_args()
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)  # the benchmarks' seeds start at torch.initial_seed()
    args.out.mkdir(parents=True, exist_ok=True)
    scenario = args.scenario
    if args.effect is not None:
        scenario = str(measured(Path(args.scenario), args.effect, args.out / "scenario"))
    ctx = BenchContext(size="quick", seeds=args.seeds, out_dir=args.out, device="cpu", scenario=scenario)
    out = run_b4(ctx, bench_size("quick"), json.loads(args.extra))
    (args.out / "b4.json").write_text(json.dumps(out, indent=1, default=str))
    for arm, v in out["variants"].items():
        m, t, b = v["mae_db"], v["truth_mae_db"], v["unseen_bias_db"]
        print(
            f"{arm:9s} SSB {m['ssb']['all']:.2f} / {m['ssb']['changed']:.2f}, CSI-RS {m['csi']['all']:.2f} / "
            f"{m['csi']['changed']:.2f}; truth {t['ssb']['all']:.2f}, {t['csi']['all']:.2f}; "
            f"unseen bias {b['ssb']:+.2f} / {b['csi']:+.2f}; {v['train_time_s']:.0f} s"
        )
    print("prior gain [dB] per seed:", out["prior_gain_per_seed_db"], "mean:", out["prior_gain_db"])


if __name__ == "__main__":
    main()
