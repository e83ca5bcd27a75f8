"""Variants of RF-LSCM's post-training corrections on one trained B1 quick model (issue 28).

The corrections (level, anchors, posterior) are fitted after training from the trained field, so a variant of
them needs no new training: train once (``train``), then refit and evaluate only the corrections (``refit``).
Each row is B1 quick's round-2 MAE [dB] (SSB / CSI-RS × all / changed cells) of RF-LSCM with the variant, next to
WNOMP at its selected settings (as B1 and ``rflscm demo`` choose them) and the difference RF-LSCM − WNOMP.

Usage (from the repository root, one thread: deterministic and independent of the machine's load):

    PYTHONPATH=src python experiments/posterior_variants.py train SCENARIO OUT.pt [SEED] [CONFIG_JSON]
    PYTHONPATH=src python experiments/posterior_variants.py refit SCENARIO OUT.pt '{}' '{"wnomp_atoms": true}' ...

``train`` runs B1 quick's RF-LSCM (training seed SEED, default 0; 1500 steps) and WNOMP on ``SCENARIO`` and saves the trained model with
both MAE tables to ``OUT.pt``; ``refit`` lays each JSON object over the model's ``corrections`` config section,
refits the corrections and prints one ``RESULT {json}`` line per variant.  Keys that start with ``_`` set the
posterior's constants for that variant instead: ``_priors`` (``WNOMP_PRIORS``, a list of [centre, field] pairs),
``_atoms`` (``WNOMP_ATOMS``, a list), ``_lambdas`` (the candidate λ list), ``_mix_weights`` (``MIX_WEIGHTS``, the candidate
weights of WNOMP's APS in the dB mix of the posterior pairs; ``[0]``: no mix), ``_silence`` (false: no cap from round
1's silence, ``RoundOneCensor``).
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from rflscm.bench import BenchContext
from rflscm.bench.harness import load_bench_data, quick_size, train_and_evaluate
from rflscm.eval import AdjustProtocol, run_evaluation
from rflscm.eval.cache import APSCache

ROWS = [(bt, which) for bt in ("ssb", "csi") for which in ("all", "changed")]


def _table(mae: dict) -> dict[str, float]:
    return {f"{bt}_{which}": round(float(mae[bt][which]), 3) for bt, which in ROWS}


def _data(scenario: str):
    return load_bench_data(BenchContext("quick", 1, Path("/tmp/posterior_variants"), "cpu", scenario), quick_size())


def train(scenario: str, out: str, seed: int = 0, extra: dict | None = None) -> None:
    data = _data(scenario)
    run = train_and_evaluate(data, "rflscm", AdjustProtocol(), extra, seed=seed)
    wnomp = train_and_evaluate(data, "wnomp", AdjustProtocol(), seed=0)
    saved = {
        "model": run.model,
        "rflscm": _table(run.metrics["mae_db"]),
        "wnomp": _table(wnomp.metrics["mae_db"]),
        "oracle": _table(run.metrics["oracle_mae_db"]),
        "train_time_s": run.train_time_s,
        "unseen_blend": run.model.run_info.get("unseen_blend"),
    }
    torch.save(saved, out)
    print("TRAINED", json.dumps({k: v for k, v in saved.items() if k != "model"}), flush=True)


def refit(scenario: str, path: str, variants: list[dict]) -> None:
    data = _data(scenario)
    saved = torch.load(path, weights_only=False)
    model, wnomp = saved["model"], saved["wnomp"]
    if not hasattr(model, "_blend_grids"):  # pickled before the unseen-grid blend existed: its hold-out is empty
        model._blend_grids = np.zeros(0, np.int64)
    if not hasattr(model, "_silence_dbm"):  # pickled before round 1's silence table: what _prepare now sets
        from rflscm.data.reporting import rule_of

        sinr = rule_of(data.scenario, "ssb").rule == "sinr"
        model._silence_dbm = None if sinr else float(data.scenario.meta.rsrp_threshold_dbm)
    silence = model._silence_dbm
    print("WNOMP", json.dumps(wnomp), "TRAINED-WITH", json.dumps(saved["rflscm"]), flush=True)
    base = model.config
    from rflscm.models.rflscm import corrections as module
    from rflscm.models.rflscm import posterior as post_mod

    mix_default = module.MIX_WEIGHTS

    for variant in variants:
        consts = {k: v for k, v in variant.items() if k.startswith("_")}
        module.WNOMP_PRIORS = tuple(tuple(map(float, c)) for c in consts.get("_priors", post_mod.WNOMP_PRIORS))
        module.WNOMP_ATOMS = tuple(consts.get("_atoms", post_mod.WNOMP_ATOMS))
        module.LAMBDAS = tuple(consts.get("_lambdas", post_mod.LAMBDAS))
        module.MIX_WEIGHTS = tuple(map(float, consts.get("_mix_weights", mix_default)))
        model._silence_dbm = silence if consts.get("_silence", True) else None
        knobs = {k: v for k, v in variant.items() if not k.startswith("_")}
        corrections = dataclasses.replace(base.corrections, **knobs)
        model.config = dataclasses.replace(base, corrections=corrections)
        t0 = time.perf_counter()
        model.finish_training()
        fit_s = time.perf_counter() - t0
        mae = _table(
            run_evaluation(APSCache(model), data.scenario, AdjustProtocol(), oracle=data.oracle).metrics["mae_db"]
        )
        posterior = model.corrections.posterior
        row = {
            "variant": variant,
            "mae": mae,
            "minus_wnomp": {k: round(mae[k] - wnomp[k], 3) for k in mae},
            "lam": None if posterior is None else posterior.lam,
            "candidates": None if posterior is None else int(posterior.bins.shape[1]),
            "scores": None if posterior is None else {str(k): round(v, 4) for k, v in posterior.scores.items()},
            "atom_scores": None
            if posterior is None
            else {str(k): round(v, 4) for k, v in posterior.atom_scores.items()},
            "groups": None if posterior is None else posterior.groups,
            "fit_s": round(fit_s, 1),
            "mix": None
            if model.corrections.mix is None
            else {"pairs": len(model.corrections.mix.index), **model.corrections.mix.scores},
        }
        print("RESULT", json.dumps(row), flush=True)


if __name__ == "__main__":
    torch.set_num_threads(1)
    if sys.argv[1] == "train":
        train(
            sys.argv[2],
            sys.argv[3],
            int(sys.argv[4]) if len(sys.argv) > 4 else 0,
            json.loads(sys.argv[5]) if len(sys.argv) > 5 else None,
        )
    else:
        refit(sys.argv[2], sys.argv[3], [json.loads(v) for v in sys.argv[4:]])
