"""Which reporting rule's bounds the missing-beam penalty pays for (docs/DECISIONS.md, issue 15 ablations).

Trains RF-LSCM with B5's quick setup (one site, 150 grids, 400 steps of 32 pairs, α_P as given) on a
scenario and prints its round-2 MAE on the reported beams, against the noiseless truth on every beam,
the validation MAE and the share of missing beams above their bound, for one variant:

* ``both``: the penalty on every missing beam (the default);
* ``ssb`` / ``csi``: the bounds of the other beam type dropped, so only this beam type is penalised;
* ``ramp``: α_P grows linearly from 0 over the first 40 % of the schedule.

(``no_detection``, bounding undetected SSB beams by r_th alone, lives on branch ``i15-detection-bounds``.)

    python scripts/penalty_probe.py src/rflscm/assets/scenarios/default csi 0.5
"""

from __future__ import annotations

import json
import sys

import numpy as np
import torch

import rflscm.models.pairs as pairs_module
import rflscm.models.rflscm.model as rflscm_module
from rflscm.bench import BenchContext
from rflscm.bench.b05_alpha_p import EXTRA
from rflscm.bench.harness import bench_size, load_bench_data, merge, train_and_evaluate
from rflscm.bench.report import record
from rflscm.eval import AdjustProtocol

RAMP_SHARE = 0.4


def _only(beam_type: str) -> None:
    original = pairs_module.missing_bounds

    def bounds(scenario, round, bt, pairs, rsrp_dbm):  # type: ignore[no-untyped-def]
        out = original(scenario, round, bt, pairs, rsrp_dbm)
        return out if bt == beam_type else np.full_like(out, np.nan)

    pairs_module.missing_bounds = bounds


def _ramp() -> None:
    cls = rflscm_module.RFLSCM
    losses, loss = cls.training_losses, cls._loss

    def training_losses(self, pairs, position):  # type: ignore[no-untyped-def]
        self._probe_position = position
        return losses(self, pairs, position)

    def _loss(self, a_sel, x, pairs):  # type: ignore[no-untyped-def]
        out = loss(self, a_sel, x, pairs)
        scale = min(1.0, getattr(self, "_probe_position", 1.0) / RAMP_SHARE)
        out["total"] = out["total"] + self.config.loss.missing_penalty * (scale - 1.0) * out["penalty"]
        return out

    cls.training_losses, cls._loss = training_losses, _loss


def main(scenario: str, variant: str, alpha: float) -> None:
    torch.set_num_threads(1)
    if variant in ("ssb", "csi"):
        _only(variant)
    elif variant == "ramp":
        _ramp()
    elif variant != "both":
        raise SystemExit(f"variant must be both, ssb, csi or ramp (got {variant!r})")
    ctx = BenchContext(size="quick", seeds=1, out_dir="penalty-probe", device="cpu", scenario=scenario)
    data = load_bench_data(ctx, bench_size("quick"))
    torch.manual_seed(0)
    over = merge(EXTRA["quick"], {"loss": {"missing_penalty": alpha}})
    result = train_and_evaluate(data, "rflscm", AdjustProtocol(), over, 0, "cpu")
    rec = record(result)
    summary = {
        "variant": variant,
        "alpha_p": alpha,
        "mae_db": rec["mae_db"],
        "truth_mae_db": rec["truth_mae_db"],
        "val_mae_db": rec["val_mae_db"],
        "missing_above_bound": result.metrics["missing_above_bound"]["model"],
    }
    print(json.dumps(summary))


if __name__ == "__main__":
    if len(sys.argv) not in (3, 4):
        raise SystemExit(__doc__)
    main(sys.argv[1], sys.argv[2], float(sys.argv[3]) if len(sys.argv) == 4 else 0.5)
