"""A checkpoint's pass after training rerun (no clock) with each pair's anchor as the mean (the model's), the median
or a Huber M-estimate of its residuals, nothing retrained (issue 28; DECISIONS, "The anchor is its reports' mean").

Usage (from the repository root, which puts ``pass_model.py`` on the path):

    PYTHONPATH=src python experiments/anchor_form.py CHECKPOINT SCENARIO [mean,median,huber1.5]

    PYTHONPATH=src python experiments/anchor_form.py cli median --threads 1 bench b6 --size quick --out OUT

(the second form: any ``rflscm`` command with the anchors' form patched in).  ``median`` is the form before the mean
(its noise v_k drawn from the pooled residuals, as it was); ``huberC`` a Huber estimate with its corner at
C × 2.5 dB (its noise drawn the same way).  One ``FORM {json}`` line per form: κ and
round 2's MAE over the pairs with round-1 reports (``evaluate``'s ``seen`` rows).
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable

import numpy as np
import pandas as pd
import torch
from pass_model import model_before_its_pass
from shape_level_split import seen_rows

import rflscm.models.rflscm.anchors as anchors
import rflscm.models.rflscm.corrections as corrections
from rflscm.data import load_scenario
from rflscm.eval import AdjustProtocol, run_evaluation

NOISE_DB = 2.5
"""The reports' noise scale [dB] a Huber corner is a multiple of."""
DRAWS = 4096


def huber(values: np.ndarray, corner: float) -> np.ndarray:
    """Huber location of each row of ``values [P, M]`` (NaN = no report), from the median, 20 reweightings."""
    m = np.nanmedian(values, axis=1)
    for _ in range(20):
        r = np.nan_to_num(values - m[:, None])
        w = np.where(np.isnan(values), 0.0, np.minimum(1.0, corner * NOISE_DB / np.maximum(np.abs(r), 1e-9)))
        m = (w * np.nan_to_num(values)).sum(1) / np.maximum(w.sum(1), 1e-9)
    return m


def estimator(form: str) -> Callable[[np.ndarray], np.ndarray]:
    if form == "median":
        return lambda v: np.nanmedian(v, axis=1)
    if form.startswith("huber"):
        return lambda v: huber(v, float(form[5:]))
    raise ValueError(form)


def patched(form: str) -> tuple[Callable, Callable]:
    """``report_mean`` and ``mean_noise`` replaced by the form's estimate and the variance of it over k draws."""
    est = estimator(form)

    def location(resid: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        values = torch.where(mask, resid, torch.nan).cpu().double().numpy()
        out = np.zeros(len(values))
        some = mask.any(1).cpu().numpy()
        out[some] = est(values[some])
        return torch.as_tensor(out, dtype=resid.dtype, device=resid.device)

    def noise(pool: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
        gen = torch.Generator().manual_seed(0)
        var = {}
        for k in sorted({int(c) for c in counts.tolist()}):
            draws = pool[torch.randint(pool.numel(), (DRAWS, k), generator=gen)].double().numpy()
            var[k] = float(np.var(est(draws)))
        return torch.tensor([var[int(c)] for c in counts.tolist()], dtype=torch.float64)

    return location, noise


def main(checkpoint: str, scenario: str, forms: list[str]) -> None:
    torch.set_num_threads(1)
    sc = load_scenario(scenario)
    r1_index = {bt: pd.MultiIndex.from_frame(sc.rsrp_table(1, bt)[0]) for bt in ("ssb", "csi")}
    own = corrections.report_mean, anchors.mean_noise
    for form in forms:
        if form != "mean":
            corrections.report_mean, anchors.mean_noise = patched(form)
        model = model_before_its_pass(sc, checkpoint)
        model.finish_training()
        corrections.report_mean, anchors.mean_noise = own
        evaluation = run_evaluation(model, sc, AdjustProtocol(), oracle=None)
        row = {"form": form, "kappa": round(model.corrections.anchor_kappa, 2)}
        print("FORM", json.dumps(row | seen_rows(evaluation, r1_index)), flush=True)


def cli(form: str, args: list[str]) -> None:
    """The ``rflscm`` command with the anchors' ``form`` patched in (training and benches alike)."""
    from rflscm.cli import main as rflscm_main

    corrections.report_mean, anchors.mean_noise = patched(form)
    sys.argv = ["rflscm", *args]
    rflscm_main()


if __name__ == "__main__":
    if sys.argv[1] == "cli":
        cli(sys.argv[2], sys.argv[3:])
    else:
        main(sys.argv[1], sys.argv[2], sys.argv[3].split(",") if len(sys.argv) > 3 else ["mean", "median", "huber1.5"])
