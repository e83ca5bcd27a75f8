"""evaluate(): stable keys, numbers recomputed independently, the oracle floor and the trivial baseline."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from eval_helpers import GRID, on_grid_truth_scenario, simulate

from rflscm.data import load_scenario
from rflscm.eval import AdjustProtocol, UnseenProtocol, evaluate, fit_with_protocol, run_evaluation
from rflscm.eval.metrics import changed_cells
from rflscm.models import MODEL_REGISTRY

DOCUMENTED_KEYS = [
    "mae_db.ssb.all",
    "mae_db.ssb.changed",
    "mae_db.csi.all",
    "mae_db.csi.changed",
    "oracle_mae_db.ssb.all",
    "oracle_mae_db.ssb.changed",
    "oracle_mae_db.csi.all",
    "oracle_mae_db.csi.changed",
    "trivial_mae_db.ssb.all",
    "trivial_mae_db.ssb.changed",
    "trivial_mae_db.csi.all",
    "trivial_mae_db.csi.changed",
    "aps.nmse_db",
    "aps.nmse_db_median",
    "aps.angle_error_deg",
    "aps.top_k",
    "aps.pairs",
    "unseen.mae_db.ssb",
    "unseen.mae_db.csi",
    "unseen.oracle_mae_db.ssb",
    "unseen.trivial_mae_db.csi",
    "unseen.pairs.ssb",
    "counts.ssb.test_pairs",
    "counts.ssb.scored_pairs",
    "counts.ssb.beams",
    "counts.ssb.changed_beams",
    "counts.csi.beams",
    "counts.cells",
    "counts.changed_cells",
    "model.name",
    "model.supports_unseen_grids",
    "model.fingerprint",
    "model.fit",
    "protocol.name",
    "test_round",
    "scenario.name",
    "unsupported",
    "timing_s.predict",
    "noise_floor_mae_db.ssb.all",
    "noise_floor_mae_db.csi.changed",
    "bias_db.ssb.all",
    "bias_db.csi.changed",
    "missing_above_bound.model.ssb",
    "missing_above_bound.trivial.csi",
    "missing_above_bound.model.pooled",
    "unseen.noise_floor_mae_db.ssb",
    "unseen.bias_db.csi",
    "truth_mae_db.model.ssb.all",
    "truth_mae_db.oracle.csi.changed",
    "truth_mae_db.trivial.ssb.all",
]


def get(tree: dict, dotted: str):
    for key in dotted.split("."):
        tree = tree[key]
    return tree


def _wnomp(scenario, protocol=None):
    model = MODEL_REGISTRY["wnomp"].build(None, GRID, "cpu")
    fit_with_protocol(model, scenario, protocol, progress=False)
    return model


@pytest.fixture(scope="module")
def adjust_run(sim_scenario):
    model = _wnomp(sim_scenario)
    return model, run_evaluation(model, sim_scenario)


def test_documented_keys_are_present_and_json_ready(adjust_run, sim_scenario) -> None:
    _model, evaluation = adjust_run
    metrics = evaluation.metrics
    for key in DOCUMENTED_KEYS:
        get(metrics, key)  # KeyError names the missing one
    assert json.loads(json.dumps(metrics)) == metrics
    assert metrics["protocol"] == {"name": "adjust", "test_round": 2}
    assert metrics["counts"]["changed_cells"] == changed_cells(sim_scenario).tolist() != []
    floor = metrics["noise_floor_mae_db"]["ssb"]["all"]  # ideal regime: 2 dB noise + 1 dB steps on the truth
    assert floor is not None and 1.0 < floor < 2.2 and metrics["oracle_mae_db"]["ssb"]["all"] >= floor - 0.3
    for cell, entry in metrics["per_cell"].items():
        assert entry["changed"] == (int(cell) in metrics["counts"]["changed_cells"])
        assert set(entry) == {"changed", "ssb", "csi", "oracle", "trivial", "noise_floor", "counts"}


def test_truth_mae_scores_every_beam_above_threshold_against_the_noiseless_truth(adjust_run, sim_scenario) -> None:
    _model, evaluation = adjust_run
    metrics = evaluation.metrics
    truth = pd.read_parquet(sim_scenario.root / sim_scenario.meta.truth / "rsrp_noiseless.parquet")
    r_th = sim_scenario.meta.rsrp_threshold_dbm
    for beam_type in ("ssb", "csi"):
        res = evaluation.beams[beam_type]
        rows = res.pairs[res.scored].reset_index(drop=True)
        predicted = res.model[res.scored]
        t = truth[(truth["round"] == 2) & (truth["beam_type"].astype(str) == beam_type)]
        t = t[t["rsrp_dbm"] >= r_th].merge(
            rows.reset_index()[["index", "cell_id", "grid_id"]], on=["cell_id", "grid_id"]
        )
        expected = np.abs(predicted[t["index"].to_numpy(), t["beam_id"].to_numpy()] - t["rsrp_dbm"].to_numpy())
        assert metrics["truth_mae_db"]["model"][beam_type]["all"] == pytest.approx(np.nanmean(expected))
        assert np.isfinite(expected).sum() > 0 and (t["rsrp_dbm"] >= r_th).all()
        # the oracle is the truth's APS through the same antenna (ideal regime): far closer than any fit
        oracle = metrics["truth_mae_db"]["oracle"][beam_type]["all"]
        assert oracle is not None and oracle < 0.5 * metrics["truth_mae_db"]["trivial"][beam_type]["all"]


def test_mae_recomputed_independently_and_wnomp_beats_trivial(adjust_run, sim_scenario) -> None:
    model, evaluation = adjust_run
    metrics = evaluation.metrics
    for beam_type in ("ssb", "csi"):
        pairs, measured = sim_scenario.rsrp_table(2, beam_type)
        seen = set(zip(model.cell_ids, model.grid_ids))
        keep = np.array([(c, g) in seen for c, g in zip(pairs["cell_id"], pairs["grid_id"])]) & np.isfinite(
            measured
        ).any(1)
        predicted = model.predict_rsrp(sim_scenario, 2, beam_type, pairs[keep].reset_index(drop=True))
        err = np.abs(predicted - measured[keep][:, : predicted.shape[1]])
        assert metrics["mae_db"][beam_type]["all"] == pytest.approx(np.nanmean(err))
        assert metrics["counts"][beam_type]["beams"] == np.isfinite(err).sum()
        assert metrics["mae_db"][beam_type]["all"] < metrics["trivial_mae_db"][beam_type]["all"]
        changed = np.isin(pairs[keep]["cell_id"], metrics["counts"]["changed_cells"])
        assert metrics["mae_db"][beam_type]["changed"] == pytest.approx(np.nanmean(err[changed]))
    assert metrics["aps"]["pairs"] > 0 and metrics["aps"]["angle_error_deg"] > 0


def test_oracle_is_exact_without_noise_and_not_with_it(tmp_path) -> None:
    for noise_db, check in ((0.0, lambda v: v < 1e-3), (2.0, lambda v: v > 0.5)):
        scenario = load_scenario(on_grid_truth_scenario(tmp_path / f"noise{noise_db}", noise_db))
        metrics = evaluate(_wnomp(scenario), scenario)
        for beam_type in ("ssb", "csi"):
            value = metrics["oracle_mae_db"][beam_type]["all"]
            assert check(value), (noise_db, beam_type, value)
            assert check(metrics["oracle_mae_db"][beam_type]["changed"])  # cell 12 tilted in round 2: A′ is exact too


def test_procedural_oracle_floor_is_binning_only_without_noise(tmp_path, sim_scenario) -> None:
    quiet = load_scenario(simulate(tmp_path / "quiet", noise_sigma_db=0.0, quantization_db=0.0))
    floor = evaluate(_wnomp(quiet), quiet)["oracle_mae_db"]
    noisy = evaluate(_wnomp(sim_scenario), sim_scenario)["oracle_mae_db"]
    assert floor["ssb"]["all"] < 1.5  # only angular binning (6° × 10° bins; narrow CSI-RS beams suffer more)
    for beam_type in ("ssb", "csi"):
        assert noisy[beam_type]["all"] > floor[beam_type]["all"] + 0.3


def test_unseen_protocol_with_wnomp_says_it_cannot_answer(sim_scenario) -> None:
    protocol = UnseenProtocol(fraction=0.2, seed=1)
    model = _wnomp(sim_scenario, protocol)
    metrics = evaluate(model, sim_scenario)
    assert metrics["protocol"]["name"] == "unseen" and metrics["test_round"] == 1
    assert metrics["mae_db"]["ssb"]["all"] is None and metrics["unseen"]["mae_db"]["ssb"] is None
    assert "no notion of unseen grids" in metrics["unsupported"]
    assert metrics["counts"]["ssb"]["scored_pairs"] == 0 < metrics["counts"]["ssb"]["test_pairs"]
    assert metrics["unseen"]["pairs"]["ssb"] == metrics["counts"]["ssb"]["test_pairs"]
    assert metrics["trivial_mae_db"]["ssb"]["all"] > 0 and metrics["oracle_mae_db"]["ssb"]["all"] > 0
    assert metrics["mae_db"]["ssb"]["changed"] is None  # round 1: nothing changed
    assert metrics["aps"]["pairs"] == 0


def test_no_oracle_without_truth(sim_scenario) -> None:
    model = _wnomp(sim_scenario)
    metrics = evaluate(model, sim_scenario, AdjustProtocol(), oracle=None)
    assert metrics["oracle_mae_db"]["ssb"]["all"] is None and metrics["aps"]["nmse_db"] is None
    assert metrics["mae_db"]["ssb"]["all"] is not None


def test_unseen_bias_is_the_mean_signed_error_over_pairs_round_1_never_reported(sim_scenario) -> None:
    from rflscm.eval.oracle import OracleModel

    oracle = OracleModel.for_scenario(sim_scenario, GRID, "cpu")
    evaluation = run_evaluation(oracle, sim_scenario, AdjustProtocol(), oracle=None)
    for beam_type, res in evaluation.beams.items():
        unseen = ~res.seen
        err = (res.model - res.measured)[unseen]
        expected = float(np.nanmean(err)) if np.isfinite(err).any() else None
        assert evaluation.metrics["unseen"]["bias_db"][beam_type] == pytest.approx(expected)
        assert evaluation.metrics["unseen"]["pairs"][beam_type] == int(unseen.sum())
        assert expected is not None  # round 2 reports pairs round 1 did not (the fixture's changed cells)


def test_missing_above_bound_counts_each_type_and_pools_them_by_beams() -> None:
    from rflscm.eval.evaluate import BeamResult, _above_bound

    def result(bound: np.ndarray, model: np.ndarray, scored: np.ndarray) -> BeamResult:
        n = len(bound)
        return BeamResult(
            pairs=pd.DataFrame({"cell_id": np.zeros(n, int), "grid_id": np.arange(n)}),
            measured=np.full_like(bound, np.nan),
            model=model,
            trivial=np.full_like(bound, -200.0),
            oracle=None,
            seen=np.ones(n, bool),
            scored=scored,
            changed=np.zeros(n, bool),
            bound=bound,
        )

    nan = np.nan
    # SSB: 4 missing beams on scored rows (one above its bound); the unscored row's beam is left out
    ssb = result(
        np.array([[-100.0, -100.0], [-90.0, -90.0], [-80.0, nan]]),
        np.array([[-95.0, -105.0], [-91.0, -99.0], [0.0, 0.0]]),
        np.array([True, True, False]),
    )
    # CSI-RS: 2 missing beams, both above
    csi = result(np.array([[-100.0, nan], [-100.0, nan]]), np.array([[-50.0, 0.0], [-60.0, 0.0]]), np.ones(2, bool))
    out = _above_bound({"ssb": ssb, "csi": csi})
    assert out["model"]["ssb"] == pytest.approx(1 / 4) and out["model"]["csi"] == 1.0
    assert out["model"]["pooled"] == pytest.approx(3 / 6)  # by beams, not the mean of the two shares (0.625)
    assert out["trivial"]["pooled"] == 0.0 and out["oracle"]["ssb"] is None and out["oracle"]["pooled"] is None


def test_a_progress_bar_counts_the_cells_only_when_asked(adjust_run, sim_scenario, monkeypatch) -> None:
    """``run_evaluation(progress=True)`` counts the test's cells on a bar shown on a terminal only (tqdm's
    ``disable=None``); without it the bar is off."""
    import importlib

    module = importlib.import_module("rflscm.eval.evaluate")
    model, evaluation = adjust_run
    made: list[dict] = []
    real = module.tqdm

    def spy(iterable, **kwargs):  # type: ignore[no-untyped-def]
        items = list(iterable)
        made.append({**kwargs, "count": len(items)})
        return real(items, **kwargs)

    monkeypatch.setattr(module, "tqdm", spy)
    run_evaluation(model, sim_scenario, max_aps_pairs=0, progress=True)
    run_evaluation(model, sim_scenario, max_aps_pairs=0)
    cells = pd.concat([res.pairs for res in evaluation.beams.values()])["cell_id"].nunique()
    assert [m["disable"] for m in made] == [None, True]
    assert made[0]["count"] == cells >= 2 and made[0]["unit"] == "cell"


def test_the_fresh_pairs_are_grouped_by_the_calls_the_evaluation_makes(sim_scenario) -> None:
    """``tested_pairs`` keys each test pair without a round-1 report by the ``aps`` call ``run_evaluation`` will ask
    for it in (a budget's fit prices their renders by those calls): a model that answers unseen grids is asked for
    each key's pairs together, and for no two keys' pairs in one call."""
    from rflscm.eval.evaluate import tested_pairs
    from rflscm.eval.oracle import OracleModel

    # more fresh pairs: round 1 of some round-2 pairs dropped, and round 2's SSB of every other one (tested on CSI-RS
    # alone, a cell's second call)
    m = sim_scenario.measurements
    keys = pd.MultiIndex.from_frame(m[["cell_id", "grid_id"]])
    both = m[m["round"] == 2].groupby(["cell_id", "grid_id"])["beam_type"].nunique()
    picked = both[both == 2].index[::7]
    hit = keys.isin(picked)
    csi_only = keys.isin(picked[::2]) & (m["round"] == 2).to_numpy() & (m["beam_type"] == "ssb").to_numpy()
    scenario = sim_scenario.with_measurements(m[~((hit & (m["round"] == 1).to_numpy()) | csi_only)])
    known, fresh = tested_pairs(scenario, AdjustProtocol())
    assert fresh.calls is not None and known > len(fresh) >= len(picked) >= 4
    per_cell = pd.Series(fresh.calls).groupby(fresh.cell_ids).nunique()
    assert (per_cell == 2).any()  # some cells' fresh pairs come in two calls (SSB's, then CSI-RS's own)
    where = scenario.grids.set_index("grid_id")[["x", "y", "z"]]
    key_of = {
        (int(c), *np.round(xyz, 3).tolist()): int(k)
        for c, xyz, k in zip(fresh.cell_ids, fresh.grid_xyz, fresh.calls, strict=True)
    }
    model = OracleModel.for_scenario(scenario, GRID)
    asked: list[set[int]] = []
    inner_aps = model.aps

    def spy(cell_ids, grid_ids, grid_xyz=None):  # type: ignore[no-untyped-def]
        xyz = where.loc[np.asarray(grid_ids)].to_numpy() if grid_xyz is None else np.asarray(grid_xyz)
        pairs = [(int(c), *np.round(p, 3).tolist()) for c, p in zip(cell_ids, xyz, strict=True)]
        asked.append({key_of[p] for p in pairs if p in key_of})
        return inner_aps(cell_ids, grid_ids, grid_xyz)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(model, "aps", spy)
        run_evaluation(model, scenario, AdjustProtocol(), oracle=None)
    keys = [k for k in asked if k]
    assert all(len(k) == 1 for k in keys)  # no call mixes two keys' pairs
    assert sorted(k.pop() for k in keys) == sorted(np.unique(fresh.calls).tolist())  # each key asked in one call


def test_each_cells_aps_are_remembered_only_while_its_pairs_are_predicted(adjust_run, sim_scenario) -> None:
    """A plain model is asked for each distinct test pair once, its APS cached per cell (memory grows with a cell's
    pairs, not the network's) and only the APS metrics' pairs kept; the metrics equal those read through one shared
    cache (a benchmark's, or the one Ray workers fill)."""
    from rflscm.eval.cache import APSCache

    model, shared = adjust_run
    asked: list[tuple[int, int]] = []
    held: dict[int, set[int]] = {}  # per cache: the cells it was asked for
    alive: list[APSCache] = []  # a freed cache's id can be reused by the next one; holding each keeps ids distinct
    aps = APSCache.aps

    def spy(self, cell_ids, grid_ids, grid_xyz=None):  # type: ignore[no-untyped-def]
        if id(self) not in held:
            alive.append(self)
        held.setdefault(id(self), set()).update(np.asarray(cell_ids).tolist())
        return aps(self, cell_ids, grid_ids, grid_xyz)

    inner_aps = model.aps

    def counted(cell_ids, grid_ids, grid_xyz=None):  # type: ignore[no-untyped-def]
        asked.extend(zip(np.asarray(cell_ids).tolist(), np.asarray(grid_ids).tolist(), strict=True))
        return inner_aps(cell_ids, grid_ids, grid_xyz)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(APSCache, "aps", spy)
        mp.setattr(model, "aps", counted)
        evaluation = run_evaluation(model, sim_scenario, max_aps_pairs=7)
    per_cell = [cells for cells in held.values() if len(cells) == 1]
    assert len(per_cell) == len(held) - 1 >= 2  # one cache per cell, and the kept one the APS metrics read
    assert len(asked) == len(set(asked))  # no pair asked twice, the APS metrics' pairs included
    tested = {bt: res.pairs[res.scored] for bt, res in shared.beams.items()}
    assert set(asked) == set(map(tuple, pd.concat(tested.values())[["cell_id", "grid_id"]].to_numpy().tolist()))
    assert evaluation.metrics["aps"]["pairs"] == 7
    again = run_evaluation(APSCache(model), sim_scenario, max_aps_pairs=7).metrics
    drop = ("timing_s",)
    assert {k: v for k, v in evaluation.metrics.items() if k not in drop} == {
        k: v for k, v in again.items() if k not in drop
    }
    for key in ("mae_db", "oracle_mae_db", "trivial_mae_db", "per_cell", "unseen"):
        assert evaluation.metrics[key] == shared.metrics[key]


def test_seen_block_scores_an_unseen_capable_model_on_the_pairs_wnomp_answers(sim_scenario) -> None:
    """The oracle answers every pair; its ``seen`` block is over the pairs WNOMP scores, and WNOMP's equals its own
    all-pairs block (it answers nothing else)."""
    from rflscm.eval.oracle import OracleModel

    oracle = OracleModel.for_scenario(sim_scenario, GRID, "cpu")
    evaluation = run_evaluation(oracle, sim_scenario, AdjustProtocol(), oracle=None)
    wnomp = evaluate(_wnomp(sim_scenario), sim_scenario)
    for beam_type, res in evaluation.beams.items():
        seen = evaluation.metrics["seen"]
        err = np.abs(res.model - res.measured)[res.seen]
        assert seen["mae_db"][beam_type]["all"] == pytest.approx(float(np.nanmean(err)))
        assert seen["mae_db"][beam_type]["all"] != pytest.approx(evaluation.metrics["mae_db"][beam_type]["all"])
        assert seen["pairs"][beam_type] == wnomp["counts"][beam_type]["scored_pairs"]
        assert seen["pairs"][beam_type] + evaluation.metrics["unseen"]["pairs"][beam_type] == len(res.pairs)
        assert wnomp["seen"]["mae_db"][beam_type] == wnomp["mae_db"][beam_type]
        assert wnomp["seen"]["trivial_mae_db"][beam_type] == wnomp["trivial_mae_db"][beam_type]
