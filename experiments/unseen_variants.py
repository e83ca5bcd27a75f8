"""Variants of RF-LSCM's predictions at unseen grids on one trained B6 quick model (issue 28).

B6 quick holds out 20 % of the grids entirely; at those grids no pair has an anchor or a posterior, so the field
(with each cell's level) predicts alone.  The corrections are fitted after training, so a variant of what applies
at unseen grids needs no new training: train once (``train``), then refit the corrections with each variant laid
over the model's ``corrections`` config section and evaluate B6's unseen MAE (``refit``).

Usage (from the repository root, one thread: deterministic and independent of the machine's load):

    PYTHONPATH=src python experiments/unseen_variants.py train SCENARIO OUT.pt [SEED] [FRACTION] [CONFIG_JSON]
    PYTHONPATH=src python experiments/unseen_variants.py refit SCENARIO OUT.pt '{}' '{"pair_posterior": false}' ...

(At commit ``8b7acb5`` the model had a switch ``corrections.unseen_anchors``, measured with this script and dropped;
docs/DECISIONS.md, "Unseen grids (issue 28)".)  Each ``refit`` variant prints one ``RESULT {json}`` line: the unseen MAE, bias (prediction − measurement) [dB] and the oracle's
and trivial's MAE on the same beams, SSB and CSI-RS.

    PYTHONPATH=src python experiments/unseen_variants.py diagnose SCENARIO OUT.pt

splits the unseen MAE into each pair's level (its median error) and shape (what is left), and scores the model and
the oracle asked at each unseen pair's nearest anchored grid of the same cell instead (``DIAG`` lines), with the
distance to that grid (``DIST``).

    PYTHONPATH=src python experiments/unseen_variants.py b1split SCENARIO B1.pt

splits B1 quick's round-2 error of a model saved by ``posterior_variants.py train`` into pairs with a round-1
anchor and pairs without (``SPLIT`` lines), the model's and the oracle's MAE on the same beams.

    PYTHONPATH=src python experiments/unseen_variants.py train SCENARIO INNER.pt 0 0.35
    PYTHONPATH=src python experiments/unseen_variants.py blend SCENARIO FULL.pt INNER.pt

blends, at a pair without an anchor, the model's APS at its grid with its APS at the cell's nearest anchored grid
(``mix``: (1 − w) × own + w × nearest, linear; ``level``: the own APS scaled by (nearest / own total power)^w), and
chooses w on grids held out of training but not of the test: ``INNER.pt`` is trained with a larger hold-out
(``FRACTION`` 0.35; ``split_grids`` draws a prefix of one seeded order, so its held-out grids are B6's test grids
plus others), the weight is chosen on those others (``INNER`` lines, per w) and the chosen weight is scored on B6's
test grids with both models (``CHOSEN`` lines; ``FULL.pt`` trained with B6's own hold-out).  The test grids' MAE
for every w is printed too (``TEST`` lines), for reading only: choosing on them would tune to the test.
"""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from rflscm.bench import BenchContext
from rflscm.bench.b06_unseen import HOLDOUT
from rflscm.bench.harness import load_bench_data, quick_size, train_and_evaluate
from rflscm.eval import UnseenProtocol, run_evaluation
from rflscm.eval.cache import APSCache
from rflscm.eval.protocols import protocol_from_dict

PROTOCOL = UnseenProtocol(fraction=HOLDOUT, seed=0)


def _data(scenario: str):
    return load_bench_data(BenchContext("quick", 1, Path("/tmp/unseen_variants"), "cpu", scenario), quick_size())


def _unseen(metrics: dict) -> dict:
    u = metrics["unseen"]
    return {
        k: {bt: None if u[k].get(bt) is None else round(float(u[k][bt]), 3) for bt in ("ssb", "csi")}
        for k in ("mae_db", "bias_db", "oracle_mae_db", "trivial_mae_db", "pairs")
    }


def _loaded(path: str):
    """The trained model saved at ``path`` (pickled whole; one pickled before the unseen-grid blend existed gets its
    empty hold-out, as ``prepare`` sets it with the blend off)."""
    model = torch.load(path, weights_only=False)["model"]
    if not hasattr(model, "_blend_grids"):
        model._blend_grids = np.zeros(0, np.int64)
    return model


def train(scenario: str, out: str, seed: int = 0, fraction: float = HOLDOUT, extra: dict | None = None) -> None:
    data = _data(scenario)
    run = train_and_evaluate(data, "rflscm", UnseenProtocol(fraction=fraction, seed=0), extra, seed=seed)
    saved = {
        "model": run.model,
        "unseen": _unseen(run.metrics),
        "train_time_s": run.train_time_s,
        "unseen_blend": run.model.run_info.get("unseen_blend"),
    }
    torch.save(saved, out)
    print("TRAINED", json.dumps({k: v for k, v in saved.items() if k != "model"}), flush=True)


def refit(scenario: str, path: str, variants: list[dict]) -> None:
    data = _data(scenario)
    saved = torch.load(path, weights_only=False)
    model = _loaded(path)
    print("TRAINED-WITH", json.dumps(saved["unseen"]), flush=True)
    base = model.config
    for variant in variants:
        corrections = dataclasses.replace(base.corrections, **variant)
        model.config = dataclasses.replace(base, corrections=corrections)
        t0 = time.perf_counter()
        model.finish_training()
        fit_s = time.perf_counter() - t0
        metrics = run_evaluation(APSCache(model), data.scenario, PROTOCOL, oracle=data.oracle).metrics
        row = {"variant": variant, "unseen": _unseen(metrics), "fit_s": round(fit_s, 1)}
        print("RESULT", json.dumps(row), flush=True)


class _Nearest(APSCache):
    """A source asked at each pair's nearest anchored grid of the same cell instead (a model: its anchor and posterior
    with it; the oracle: the truth there, what a predictor that only knows the nearest measured grid could reach)."""

    def __init__(self, inner, grids, anchors, run_info) -> None:
        super().__init__(inner)
        self._info = run_info
        self._seen = {
            int(c): anchors.xs(c, level="cell_id").index.to_numpy(np.int64)
            for c in anchors.index.get_level_values("cell_id").unique()
        }
        self._xyz = grids.set_index("grid_id")[["x", "y", "z"]]

    @property
    def run_info(self):
        return self._info  # the trained model's: its protocol

    def aps(self, cell_ids, grid_ids, grid_xyz=None):
        cell_ids, grid_ids = np.asarray(cell_ids).reshape(-1), np.asarray(grid_ids).reshape(-1).copy()
        for i, (c, g) in enumerate(zip(cell_ids.tolist(), grid_ids.tolist(), strict=True)):
            seen = self._seen.get(int(c))
            if seen is None or g in seen:
                continue
            d = np.linalg.norm(self._xyz.loc[seen].to_numpy() - self._xyz.loc[g].to_numpy(), axis=1)
            grid_ids[i] = seen[int(np.argmin(d))]
        return super().aps(cell_ids, grid_ids, self._xyz.loc[grid_ids].to_numpy())


def _split(res) -> dict:
    """MAE [dB] at unseen pairs split into each pair's level (median error) and what is left (shape)."""
    rows = ~res.seen
    err = (res.model - res.measured)[rows]
    level = np.nanmedian(np.where(np.isfinite(err), err, np.nan), axis=1)
    ok = np.isfinite(err)
    shape = np.abs(err - level[:, None])[ok].mean()
    oracle = (res.oracle - res.measured)[rows]
    o_level = np.nanmedian(np.where(np.isfinite(oracle), oracle, np.nan), axis=1)
    beams = ok.sum(1)
    return {
        "mae": round(float(np.abs(err[ok]).mean()), 3),
        "bias": round(float(err[ok].mean()), 3),
        "mae_without_bias": round(float(np.abs(err[ok] - err[ok].mean()).mean()), 3),
        "shape_mae": round(float(shape), 3),
        "level_mae": round(float((np.abs(level) * beams).sum() / beams.sum()), 3),
        "oracle_shape_mae": round(float(np.abs(oracle - o_level[:, None])[ok].mean()), 3),
        "oracle_level_mae": round(float((np.abs(o_level) * beams).sum() / beams.sum()), 3),
        "beams_per_pair": round(float(beams.mean()), 2),
    }


def diagnose(scenario: str, path: str) -> None:
    """Where the unseen-grid error lies: each pair's level against its shape, and the nearest seen grid's answer."""
    data = _data(scenario)
    model = _loaded(path)
    model.finish_training()
    anchors = model.corrections.anchors
    nearest = _Nearest(model, data.scenario.grids, anchors, model.run_info)
    truth_nearest = _Nearest(data.oracle, data.scenario.grids, anchors, model.run_info)
    for label, source in (
        ("model", APSCache(model)),
        ("nearest_seen", nearest),
        ("oracle_nearest_seen", truth_nearest),
    ):
        ev = run_evaluation(source, data.scenario, PROTOCOL, oracle=data.oracle)
        print("DIAG", json.dumps({"source": label, **{bt: _split(ev.beams[bt]) for bt in ("ssb", "csi")}}), flush=True)
    pairs = ev.beams["ssb"].pairs[~ev.beams["ssb"].seen]
    xyz = nearest._xyz
    dist = [
        np.linalg.norm(xyz.loc[nearest._seen[int(c)]].to_numpy() - xyz.loc[int(g)].to_numpy(), axis=1).min()
        for c, g in zip(pairs["cell_id"], pairs["grid_id"], strict=True)
        if int(c) in nearest._seen
    ]
    print(
        "DIST",
        json.dumps({"nearest_anchored_grid_m": {"median": float(np.median(dist)), "mean": float(np.mean(dist))}}),
    )


class _Blend(APSCache):
    """At pairs without an anchor, ``base``'s APS at the pair's grid blended with its APS at the cell's nearest
    anchored grid: ``mix`` (1 − w) × own + w × nearest (linear), ``level`` own × (nearest / own total)^w."""

    def __init__(self, base: APSCache, nearest: _Nearest, kind: str, weight: float) -> None:
        super().__init__(base)
        self._base, self._nearest, self._kind, self._w = base, nearest, kind, weight

    def aps(self, cell_ids, grid_ids, grid_xyz=None):
        own = self._base.aps(cell_ids, grid_ids, grid_xyz)
        if self._w == 0.0:
            return own
        near = self._nearest.aps(cell_ids, grid_ids, grid_xyz)
        if self._kind == "mix":
            return (1.0 - self._w) * own + self._w * near
        ratio = near.sum(1, keepdim=True) / own.sum(1, keepdim=True).clamp_min(1e-30)
        return own * torch.where(ratio > 0, ratio, torch.ones_like(ratio)) ** self._w


WEIGHTS = [round(0.1 * i, 1) for i in range(11)]


def _mae_rows(ev, grids: np.ndarray) -> dict:
    """MAE [dB] of the unseen test pairs at ``grids``, SSB, CSI-RS and both pooled (beam-weighted), and the beams."""
    out, errs = {}, []
    for bt in ("ssb", "csi"):
        res = ev.beams[bt]
        rows = (~res.seen) & res.pairs["grid_id"].isin(grids).to_numpy()
        err = (res.model - res.measured)[rows]
        err = np.abs(err[np.isfinite(err)])
        errs.append(err)
        out[bt] = round(float(err.mean()), 3) if err.size else None
        out[f"{bt}_beams"] = int(err.size)
    pooled = np.concatenate(errs)
    out["both"] = round(float(pooled.mean()), 4) if pooled.size else None
    return out


def _blend_scores(data, path: str, protocol: UnseenProtocol, grids: dict[str, np.ndarray]) -> dict:
    """``{(kind, w): {name: MAE rows at grids[name]}}`` of the model at ``path`` evaluated under ``protocol``."""
    model = _loaded(path)
    corrections = dataclasses.replace(model.config.corrections, unseen_blend_grids=None)  # the model's own blend off
    model.config = dataclasses.replace(model.config, corrections=corrections)
    model.finish_training()
    base = APSCache(model)
    nearest = _Nearest(base, data.scenario.grids, model.corrections.anchors, model.run_info)
    scores = {}
    for kind in ("mix", "level"):
        for w in WEIGHTS:
            if w == 0.0 and kind == "level":
                scores[(kind, w)] = scores[("mix", 0.0)]
                continue
            ev = run_evaluation(
                _Blend(base, nearest, kind, w),
                data.scenario,
                protocol,
                oracle=data.oracle,
            )
            scores[(kind, w)] = {name: _mae_rows(ev, g) for name, g in grids.items()}
    return scores


def blend(scenario: str, full: str, inner: str) -> None:
    """Choose the blend's weight on the inner model's extra held-out grids, score it on B6's test grids."""
    data = _data(scenario)
    saved = torch.load(inner, weights_only=False)
    inner_protocol = protocol_from_dict(saved["model"].run_info["protocol"])
    test = PROTOCOL.held_out(data.scenario)
    held = inner_protocol.held_out(data.scenario)
    if not np.isin(test, held).all():
        raise SystemExit("the inner model's hold-out does not contain B6's test grids (same seed, larger fraction)")
    extra = np.setdiff1d(held, test)
    print(
        "GRIDS",
        json.dumps(
            {
                "test": len(test),
                "inner_extra": len(extra),
                "inner_training": int(len(np.unique(data.scenario.measurements["grid_id"])) - len(held)),
            }
        ),
        flush=True,
    )
    inner_scores = _blend_scores(data, inner, inner_protocol, {"extra": extra, "test": test})
    full_scores = _blend_scores(data, full, PROTOCOL, {"test": test})
    for (kind, w), row in inner_scores.items():
        print("INNER", json.dumps({"kind": kind, "w": w, **row}), flush=True)
    for (kind, w), row in full_scores.items():
        print("TEST", json.dumps({"kind": kind, "w": w, "full": row["test"]}), flush=True)
    for kind in ("mix", "level"):
        best = min(WEIGHTS, key=lambda w: inner_scores[(kind, w)]["extra"]["both"])
        print(
            "CHOSEN",
            json.dumps(
                {
                    "kind": kind,
                    "w": best,
                    "inner_test": {
                        "w0": inner_scores[(kind, 0.0)]["test"],
                        "chosen": inner_scores[(kind, best)]["test"],
                    },
                    "full_test": {
                        "w0": full_scores[(kind, 0.0)]["test"],
                        "chosen": full_scores[(kind, best)]["test"],
                    },
                }
            ),
            flush=True,
        )


def b1split(scenario: str, path: str) -> None:
    """B1 quick's round-2 error of a trained ``posterior_variants.py train`` model, split by pair: with a round-1 anchor
    (reports at that grid for that cell) or without; all and changed cells, model against oracle, and the beams."""
    from rflscm.eval import AdjustProtocol

    data = _data(scenario)
    model = _loaded(path)
    model.finish_training()
    ev = run_evaluation(APSCache(model), data.scenario, AdjustProtocol(), oracle=data.oracle)
    anchored = model.corrections.anchors.index
    for bt in ("ssb", "csi"):
        res = ev.beams[bt]
        has = np.asarray(pd.MultiIndex.from_frame(res.pairs[["cell_id", "grid_id"]]).isin(anchored), dtype=bool)
        out = {}
        for which, cells in (("all", np.ones(len(has), bool)), ("changed", res.changed)):
            for part, rows in (("anchored", has), ("unanchored", ~has)):
                sel = cells & rows
                err = (res.model - res.measured)[sel]
                orc = (res.oracle - res.measured)[sel]
                ok = np.isfinite(err) & np.isfinite(orc)
                out[f"{which}_{part}"] = {
                    "beams": int(ok.sum()),
                    "mae": round(float(np.abs(err[ok]).mean()), 3) if ok.any() else None,
                    "oracle": round(float(np.abs(orc[ok]).mean()), 3) if ok.any() else None,
                    "bias": round(float(err[ok].mean()), 3) if ok.any() else None,
                }
        print("SPLIT", bt, json.dumps(out), flush=True)


if __name__ == "__main__":
    torch.set_num_threads(1)
    if sys.argv[1] == "train":
        train(
            sys.argv[2],
            sys.argv[3],
            int(sys.argv[4]) if len(sys.argv) > 4 else 0,
            float(sys.argv[5]) if len(sys.argv) > 5 else HOLDOUT,
            json.loads(sys.argv[6]) if len(sys.argv) > 6 else None,
        )
    elif sys.argv[1] == "b1split":
        b1split(sys.argv[2], sys.argv[3])
    elif sys.argv[1] == "blend":
        blend(sys.argv[2], sys.argv[3], sys.argv[4])
    elif sys.argv[1] == "diagnose":
        diagnose(sys.argv[2], sys.argv[3])
    else:
        refit(sys.argv[2], sys.argv[3], [json.loads(v) for v in sys.argv[4:]])
