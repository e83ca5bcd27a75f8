"""``evaluate(model, scenario, protocol) -> dict``: the numbers of SPEC §5 with stable keys.

The result is a nested dict (JSON-ready); the documented names are dotted paths into it, e.g.
``mae_db.ssb.all`` is ``result["mae_db"]["ssb"]["all"]``.  A value is ``null`` (``None``) where it
does not apply (no changed cells in the test round, no ground truth, a model that cannot answer).

=====================================  ===========================================================================
key                                    meaning
=====================================  ===========================================================================
``mae_db.{ssb,csi}.all``               MAE [dB] of the model over every reported test beam it was scored on
``mae_db.{ssb,csi}.changed``           the same over the cells whose antenna changed between round 1 and the
                                       test round (``null`` when none changed, e.g. round-1 tests)
``oracle_mae_db.{ssb,csi}.{all,...}``  the *model floor*: the oracle (true APS through the nominal A′; in the field
                                       regime the APS of the test round's own UE samples): what a perfect LSCM
                                       model could reach; ``null`` without ground truth
``noise_floor_mae_db.{ssb,csi}.*``     the *noise floor*: the noiseless test-round RSRP through the real antenna
                                       (``truth/rsrp_noiseless``) against the measurements: what fading, report
                                       error and quantisation alone cost; ``null`` without ground truth
``bias_db.{ssb,csi}.{all,changed}``    the model's mean signed error (prediction − measurement) [dB]
``missing_above_bound.{model,oracle,trivial}.{ssb,csi,pooled}``  share of the test round's missing beams
                                       predicted above their bound under the reporting rule
                                       (:mod:`rflscm.data.reporting`); ``pooled``: over both beam types' beams
``truth_mae_db.{model,oracle,trivial}.{ssb,csi}.{all,changed}``  MAE [dB] against the noiseless truth
                                       (``truth/rsrp_noiseless``) over *every* beam of the scored test pairs whose
                                       true RSRP is at least r_th, reported or not: free of which beams the
                                       reporting rule let through (the measured MAE scores only those, and a
                                       top-N or SINR rule keeps the beams whose error happened to be high);
                                       ``null`` without ground truth
``trivial_mae_db.{ssb,csi}.{all,...}`` the same for the trivial baseline (each pair's mean round-1 RSRP of
                                       that beam type for every beam; the cell's mean for unseen pairs)
``per_cell[<cell_id>]``                ``changed`` (bool), ``ssb``, ``csi`` (model MAE [dB]), ``oracle.{ssb,csi}``,
                                       ``trivial.{ssb,csi}``, ``noise_floor.{ssb,csi}``, ``counts.{ssb,csi}``
``aps.nmse_db``                        mean over test pairs of the per-pair NMSE 10·log10(‖x̂ − x‖²/‖x‖²) [dB]
                                       against the true APS (``aps.nmse_db_median``: its median)
``aps.angle_error_deg``                power-weighted great-circle error [deg] between the strongest
                                       ``aps.top_k`` bins of x̂ and x (symmetric; mean over pairs)
``aps.top_k``, ``aps.pairs``           settings / number of pairs of the APS metrics
``unseen.mae_db.{ssb,csi}``            model MAE over test pairs whose (cell, grid) had no training data,
                                       ``null`` when there are none or the model has no notion of unseen grids
``unseen.{oracle,trivial}_mae_db.*``   oracle / trivial MAE over those pairs
``unseen.bias_db.{ssb,csi}``           the model's mean signed error (prediction − measurement) [dB] over them
``unseen.pairs.{ssb,csi}``             number of such pairs
``seen.{mae_db,oracle_mae_db,trivial_mae_db,noise_floor_mae_db,bias_db}.{ssb,csi}.{all,changed}``  the same
                                       blocks as above over the scored pairs that *had* training data: the pairs
                                       every model answers, so two models compare on the same pairs whatever their
                                       notion of unseen grids (``seen.pairs.{ssb,csi}``: their number)
``counts.{ssb,csi}.test_pairs``        (cell, grid) pairs with a reported beam in the test set
``counts.{ssb,csi}.scored_pairs``      pairs the model answered (MAEs are over these)
``counts.{ssb,csi}.beams``             reported beams scored; ``changed_beams`` those of changed cells
``counts.cells``, ``changed_cells``    cells in the test set; ids of the changed cells
``model``                              ``name``, ``supports_unseen_grids``, ``fingerprint``, ``fit`` (summary)
``protocol``                           the protocol spec (``name`` + settings), as stored at training
``test_round``, ``scenario``           the round tested; scenario ``name`` and ``root``
``unsupported``                        why the model could not answer (``null`` when it could)
``timing_s.{predict,oracle,aps}``      wall time of the evaluation steps [s]
=====================================  ===========================================================================

Oracle and trivial MAEs are computed over the same (cell, grid, beam) triples as the model, so the
three columns compare like for like; when the model answers nothing (WNOMP on unseen grids) they are
computed over the whole test set instead and ``counts.*.scored_pairs`` is 0.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import pandas as pd
import torch
from tqdm.auto import tqdm

from rflscm.data import BEAM_TYPES
from rflscm.data.measurements import reported_pairs
from rflscm.data.scenario import SensingCache
from rflscm.errors import ConfigError, DataError
from rflscm.eval import metrics as M
from rflscm.eval.cache import APSCache
from rflscm.eval.oracle import OracleModel
from rflscm.eval.protocols import AdjustProtocol, Protocol, TestSet, protocol_from_dict, protocol_to_dict
from rflscm.models.base import FreshPairs, UnsupportedError
from rflscm.models.source import APSSource, checked_aps, predict_rsrp

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario

MAX_APS_PAIRS = 2000


@dataclass
class BeamResult:
    """Aligned arrays of one beam type: ``[num_pairs]`` masks and ``[num_pairs, max_beams]`` RSRP [dBm]."""

    pairs: pd.DataFrame
    measured: np.ndarray
    model: np.ndarray
    trivial: np.ndarray
    oracle: np.ndarray | None
    seen: np.ndarray
    scored: np.ndarray
    changed: np.ndarray
    noiseless: np.ndarray | None = None  # [num_pairs, max_beams] dBm, truth through the real antenna
    truth_target: np.ndarray | None = None  # [num_pairs, max_beams] dBm, ``noiseless`` where >= r_th, else NaN
    bound: np.ndarray | None = None  # [num_pairs, max_beams] dBm, bound of each missing beam (NaN elsewhere)

    def rows(self) -> np.ndarray:
        """Rows the three MAEs are computed over (all test rows when the model answered none)."""
        return self.scored if self.scored.any() else np.ones(len(self.pairs), dtype=bool)


@dataclass
class Evaluation:
    """Everything :func:`run_evaluation` computed: the metrics and the arrays the report plots."""

    metrics: dict[str, Any]
    test_round: int
    beams: dict[str, BeamResult]
    aps_pairs: pd.DataFrame | None = None
    aps_est: np.ndarray | None = None  # [num_aps_pairs, num_bins]
    aps_true: np.ndarray | None = None
    extra: dict[str, Any] = field(default_factory=dict)


def resolve_protocol(model: APSSource, protocol: Protocol | str | None) -> Protocol:
    """The protocol to evaluate with: the one stored at training (``model.run_info["protocol"]``).

    ``protocol`` may name it (``"unseen"``) or give it in full; it must agree with the stored one, since
    evaluating with another split would test on training data.  A checkpoint without a stored protocol
    can only be evaluated with ``adjust`` (all round-1 data is the contract's training set).
    """
    stored = model.run_info.get("protocol")
    name = protocol if isinstance(protocol, str) or protocol is None else protocol.name
    if stored is not None:
        trained = protocol_from_dict(stored)
        if name is not None and name != trained.name:
            raise ConfigError(
                f"this model was trained for the {trained.name!r} protocol; evaluating it with {name!r} would test on "
                f"data it was trained on (or skip data it never saw); retrain with that protocol or drop --protocol."
            )
        if not isinstance(protocol, (str, type(None))) and protocol_to_dict(protocol) != stored:
            raise ConfigError(
                f"protocol settings {protocol_to_dict(protocol)} differ from the training split {stored}."
            )
        return trained
    if name not in (None, "adjust"):
        raise ConfigError(
            f"the checkpoint does not record its training split, so the {name!r} protocol cannot be checked; train with "
            f"that protocol (it is stored in the checkpoint) or evaluate with --protocol adjust."
        )
    return protocol if isinstance(protocol, AdjustProtocol) else AdjustProtocol()


def evaluate(
    model: APSSource,
    scenario: Scenario,
    protocol: Protocol | None = None,
    oracle: APSSource | str | None = "auto",
    top_k: int = 5,
    max_aps_pairs: int = MAX_APS_PAIRS,
) -> dict[str, Any]:
    """Evaluate ``model`` on ``scenario`` under ``protocol`` (default: the one stored at training, else
    ``adjust``); returns the nested metrics dict documented in the module docstring; the other arguments are
    :func:`run_evaluation`'s."""
    return run_evaluation(model, scenario, protocol, oracle, top_k, max_aps_pairs).metrics


def run_evaluation(
    model: APSSource,
    scenario: Scenario,
    protocol: Protocol | None = None,
    oracle: APSSource | str | None = "auto",
    top_k: int = 5,
    max_aps_pairs: int = MAX_APS_PAIRS,
    progress: bool = False,
) -> Evaluation:
    """Like :func:`evaluate`, keeping the predictions for the report.

    Args:
        oracle: ``"auto"`` (build :class:`~rflscm.eval.oracle.OracleModel` when the scenario has ground
            truth), an already fitted source, or ``None`` (no oracle, no APS metrics).
        top_k: bins per APS compared by the angular error.
        max_aps_pairs: APS metrics use at most this many test pairs (seeded subsample).
        progress: a progress bar over the test's cells, with its ETA (on a terminal only).
    """
    protocol = resolve_protocol(model, protocol)
    timing: dict[str, float] = {}
    train = protocol.training_scenario(scenario)
    test = protocol.test_set(scenario)
    t0 = time.perf_counter()
    oracle_model = _oracle(scenario, model, oracle, test.round)
    timing["oracle"] = time.perf_counter() - t0
    seen_index = _trained_pairs(train)
    changed = M.changed_cells(scenario, 1, test.round)
    t0 = time.perf_counter()
    aps_pairs = max_aps_pairs if oracle_model is not None else 0
    beams, unsupported, kept = _predict_tests(
        model, oracle_model, scenario, train, test, seen_index, aps_pairs, progress
    )
    for beam_type, res in beams.items():
        pairs, measured = test.tables[beam_type]
        res.changed = res.pairs["cell_id"].isin(changed).to_numpy()
        res.noiseless = _noiseless(scenario, test.round, beam_type, pairs, measured.shape[1])
        if res.noiseless is not None:
            above = res.noiseless >= scenario.meta.rsrp_threshold_dbm
            res.truth_target = np.where(above, res.noiseless, np.nan)
        res.bound = _bounds(scenario, test.round, beam_type, pairs, measured)
    skipped = {bt: int((~res.scored).sum()) for bt, res in beams.items()}
    if unsupported is None and any(skipped.values()):
        unsupported = (
            f"{model.name} has no notion of unseen grids: {skipped['ssb']} SSB and {skipped['csi']} CSI-RS test pairs "
            f"without training data were not scored."
        )
    timing["predict"] = time.perf_counter() - t0
    evaluation = Evaluation({}, test.round, beams)
    t0 = time.perf_counter()
    aps = _aps_metrics(kept, oracle_model, beams, evaluation, top_k, max_aps_pairs)
    timing["aps"] = time.perf_counter() - t0
    evaluation.metrics = _assemble(kept, scenario, protocol, test.round, beams, changed, aps, unsupported, timing)
    return evaluation


def _oracle(
    scenario: Scenario, model: APSSource, oracle: APSSource | str | None, test_round: int = 1
) -> APSSource | None:
    if oracle is None or not isinstance(oracle, str):
        return oracle
    if oracle != "auto":
        raise ConfigError(f"oracle must be 'auto', a fitted model or None (got {oracle!r}).")
    if scenario.meta.truth is None:
        return None
    try:
        # field regime: the APS of the test round's own UE samples
        return OracleModel.for_scenario(scenario, model.angle_grid, model.device, sample_round=test_round)
    except (DataError, UnsupportedError):
        return None


def tested_pairs(scenario: Scenario, protocol: Protocol) -> tuple[int, FreshPairs]:
    """How many distinct (cell, grid) pairs ``protocol``'s test set of ``scenario`` asks for that have training
    reports, and those that have none, with their grids' positions (a field model renders the latter whatever its
    pass did) and the calls :func:`run_evaluation` asks for them in: cell by cell, a pair in the call of the first
    beam type of ``BEAM_TYPES`` that tests it."""
    test = protocol.test_set(scenario)
    tables = [test.tables[bt][0][["cell_id", "grid_id"]].assign(first=i) for i, bt in enumerate(BEAM_TYPES)]
    tested = pd.concat(tables, ignore_index=True).drop_duplicates(["cell_id", "grid_id"])
    trained = _trained_pairs(protocol.training_scenario(scenario))
    known = pd.MultiIndex.from_frame(tested[["cell_id", "grid_id"]]).isin(trained)
    fresh = tested[~known]
    xyz = scenario.grids.set_index("grid_id").loc[fresh["grid_id"].to_numpy(), ["x", "y", "z"]].to_numpy(np.float64)
    cells = fresh["cell_id"].to_numpy(np.int64)
    calls = cells * len(BEAM_TYPES) + fresh["first"].to_numpy(np.int64)
    return int(known.sum()), FreshPairs(cells, xyz, calls)


def _trained_pairs(train: Scenario) -> pd.MultiIndex:
    """(cell_id, grid_id) pairs with at least one reported round-1 beam in the training data."""
    return pd.MultiIndex.from_frame(reported_pairs(train.measurements))


def _predict(
    model: APSSource, scenario: Scenario, round: int, beam_type: str, pairs: pd.DataFrame, width: int
) -> np.ndarray:
    out = np.full((len(pairs), width), np.nan)
    if len(pairs):
        pred = predict_rsrp(model, scenario, round, beam_type, pairs.reset_index(drop=True))
        out[:, : pred.shape[1]] = pred[:, :width]
    return out


def _predict_where_possible(
    model: APSSource, scenario: Scenario, round: int, beam_type: str, pairs: pd.DataFrame, width: int, ask: np.ndarray
) -> tuple[np.ndarray, np.ndarray, str | None]:
    """Predictions of the ``ask`` rows of one cell's pairs; :class:`UnsupportedError` leaves them NaN.

    Returns ``(pred [num_pairs, width], answered [num_pairs], the refusal message or None)``.
    """
    pred = np.full((len(pairs), width), np.nan)
    try:
        pred[ask] = _predict(model, scenario, round, beam_type, pairs[ask], width)
    except UnsupportedError as exc:
        return pred, np.zeros(len(pairs), dtype=bool), str(exc)
    return pred, ask.copy(), None


def _predict_tests(
    model: APSSource,
    oracle: APSSource | None,
    scenario: Scenario,
    train: Scenario,
    test: TestSet,
    seen_index: pd.MultiIndex,
    max_aps_pairs: int,
    progress: bool = False,
) -> tuple[dict[str, BeamResult], str | None, APSCache]:
    """Model, oracle and trivial predictions of every beam type's test pairs, the first refusal (SSB's before CSI-RS's),
    and the cache the APS metrics read.

    Cell by cell, both beam types of a cell one after the other (they share its sensing matrices and most of its
    pairs), each cell's APS remembered only while its pairs are predicted (a fresh :class:`APSCache` per cell), so
    that this memory grows with a cell's test pairs and not the network's.  The pairs the APS metrics will draw
    (:func:`_aps_sample` of those asked) are kept as they go by.  A ``model`` that is an :class:`APSCache` already
    (filled by workers, or shared by a benchmark) is read as it is, for every cell.  With ``progress`` a bar counts
    the cells (on a terminal only)."""
    shared = isinstance(model, APSCache)
    kept = APSCache.of(model)
    inner = kept.inner
    runs = {bt: _BeamRun(bt, *test.tables[bt], seen_index, kept, oracle) for bt in BEAM_TYPES}
    sample = _aps_sample([run.pairs[run.ask] for run in runs.values()], max_aps_pairs)
    sample_cells = sample["cell_id"].to_numpy() if sample is not None else np.zeros(0, np.int64)
    view = cast("Scenario", SensingCache(scenario, size=4))  # the scenario, with its sensing matrices kept
    cells = np.unique(np.concatenate([run.cells for run in runs.values()]))
    bar = tqdm(cells, desc=f"evaluating {inner.name}", unit="cell", leave=False, disable=None if progress else True)
    for cell in bar:  # cell by cell: model and oracle share the sensing matrices
        source = kept if shared else APSCache(inner)
        for run in runs.values():
            run.predict(cell, source, oracle, view, test.round)
        if not shared and sample is not None:
            mine = sample_cells == cell
            kept.keep(source, sample_cells[mine], sample["grid_id"].to_numpy()[mine])
    beams = {bt: run.result(train) for bt, run in runs.items()}
    return beams, next((run.why for run in runs.values() if run.why), None), kept


class _BeamRun:
    """One beam type's test pairs while :func:`_predict_tests` predicts them cell by cell."""

    def __init__(
        self,
        beam_type: str,
        pairs: pd.DataFrame,
        measured: np.ndarray,
        seen_index: pd.MultiIndex,
        model: APSSource,
        oracle: APSSource | None,
    ) -> None:
        self.beam_type, self.pairs, self.measured, self.width = beam_type, pairs, measured, measured.shape[1]
        keys = pd.MultiIndex.from_frame(pairs[["cell_id", "grid_id"]])
        self.seen = np.asarray(keys.isin(seen_index), dtype=bool) if len(pairs) else np.zeros(0, dtype=bool)
        self.ask = np.ones(len(pairs), dtype=bool) if model.supports_unseen_grids else self.seen.copy()
        self.pred = np.full((len(pairs), self.width), np.nan)
        self.answered = np.zeros(len(pairs), dtype=bool)
        self.oracle_pred = None if oracle is None else np.full((len(pairs), self.width), np.nan)
        self.cells = pairs["cell_id"].to_numpy()
        order = np.argsort(self.cells, kind="stable")
        ids, starts = np.unique(self.cells[order], return_index=True)
        self._rows = dict(zip(ids.tolist(), np.split(order, starts[1:]), strict=True))  # cell → its rows, in order
        self.why: str | None = None

    def predict(self, cell: int, model: APSSource, oracle: APSSource | None, view: Scenario, round: int) -> None:
        """Model and oracle predictions of ``cell``'s pairs (none: nothing to do)."""
        rows = self._rows.get(int(cell))
        if rows is None:
            return
        sub = self.pairs.iloc[rows].reset_index(drop=True)
        bt = self.beam_type
        p, ok, refusal = _predict_where_possible(model, view, round, bt, sub, self.width, self.ask[rows])
        self.pred[rows], self.answered[rows], self.why = p, ok, self.why or refusal
        if oracle is not None and self.oracle_pred is not None:
            self.oracle_pred[rows] = _predict_where_possible(
                oracle, view, round, bt, sub, self.width, np.ones(len(rows), bool)
            )[0]

    def result(self, train: Scenario) -> BeamResult:
        """The beam type's :class:`BeamResult` (``changed`` is set by the caller)."""
        pairs, width = self.pairs, self.width
        trivial = M.trivial_prediction(train, self.beam_type, pairs, width) if len(pairs) else np.zeros((0, width))
        return BeamResult(
            pairs,
            self.measured,
            self.pred,
            trivial,
            self.oracle_pred,
            self.seen,
            self.answered,
            np.zeros(len(pairs), dtype=bool),
        )


def _noiseless(scenario: Scenario, round: int, beam_type: str, pairs: pd.DataFrame, width: int) -> np.ndarray | None:
    """The truth's noiseless RSRP [dBm] ``[num_pairs, width]`` of the test pairs (NaN where truth left a pair out)."""
    from rflscm.data.io import read_table

    if scenario.meta.truth is None or not (scenario.root / scenario.meta.truth / "rsrp_noiseless.parquet").is_file():
        return None
    table = read_table(  # only this round's and beam type's rows (the whole truth is ~cells × grids × beams)
        scenario.root / scenario.meta.truth / "rsrp_noiseless.parquet", where={"round": round, "beam_type": beam_type}
    )
    out = np.full((len(pairs), width), np.nan)
    index = pd.MultiIndex.from_frame(pairs[["cell_id", "grid_id"]].astype("int64"))
    row = index.get_indexer(pd.MultiIndex.from_frame(table[["cell_id", "grid_id"]].astype("int64")))
    beam = table["beam_id"].to_numpy(np.int64)
    keep = (row >= 0) & (beam < width)
    out[row[keep], beam[keep]] = table["rsrp_dbm"].to_numpy(np.float64)[keep]
    return out


def _bounds(
    scenario: Scenario, round: int, beam_type: str, pairs: pd.DataFrame, measured: np.ndarray
) -> np.ndarray | None:
    from rflscm.data.reporting import missing_bounds

    try:
        return missing_bounds(scenario, round, beam_type, pairs, measured)
    except (KeyError, ValueError, IndexError):  # a test round the scenario has no table for
        return None


def _signed_mean(pred: np.ndarray, measured: np.ndarray, rows: np.ndarray) -> float | None:
    err = (pred - measured)[np.asarray(rows, dtype=bool)]
    finite = np.isfinite(err)
    return float(err[finite].mean()) if finite.any() else None


def _mae_triplet(res: BeamResult, rows: np.ndarray) -> dict[str, float | None]:
    """Model, oracle, trivial and noise-floor MAE over ``rows`` (rows with no finite model prediction drop out of the
    model's), and the model's mean signed error."""
    return {
        "model": M.mae_db(M.abs_error_db(res.model, res.measured), rows),
        "oracle": None if res.oracle is None else M.mae_db(M.abs_error_db(res.oracle, res.measured), rows),
        "trivial": M.mae_db(M.abs_error_db(res.trivial, res.measured), rows),
        "noise_floor": None if res.noiseless is None else M.mae_db(M.abs_error_db(res.noiseless, res.measured), rows),
        "bias": _signed_mean(res.model, res.measured, rows),
    }


def _truth_triplet(res: BeamResult, rows: np.ndarray) -> dict[str, float | None]:
    """Model, oracle and trivial MAE against the noiseless truth over every beam of ``rows`` above r_th."""
    if res.truth_target is None:
        return dict.fromkeys(("model", "oracle", "trivial"))
    return {
        name: None if pred is None else M.mae_db(M.abs_error_db(pred, res.truth_target), rows)
        for name, pred in (("model", res.model), ("oracle", res.oracle), ("trivial", res.trivial))
    }


def _truth_block(beams: dict[str, BeamResult], any_changed: bool) -> dict[str, dict[str, dict[str, float | None]]]:
    """``{model|oracle|trivial: {ssb|csi: {all, changed}}}`` of :func:`_truth_triplet`."""
    return _split_blocks(beams, any_changed, _truth_triplet, ("model", "oracle", "trivial"))


def _above_bound(beams: dict[str, BeamResult]) -> dict[str, dict[str, float | None]]:
    """Share of each beam type's missing test beams that model / oracle / trivial predict above their bound, and
    ``pooled``: the share over both types' missing beams together."""
    out: dict[str, dict[str, float | None]] = {k: {} for k in ("model", "oracle", "trivial")}
    counts = {k: [0, 0] for k in out}  # hits, beams
    for beam_type, res in beams.items():
        for name, pred in (("model", res.model), ("oracle", res.oracle), ("trivial", res.trivial)):
            value = None
            if res.bound is not None and pred is not None:
                has = np.isfinite(res.bound) & np.isfinite(pred) & res.rows()[:, None]
                hits, beams_here = int((pred[has] > res.bound[has]).sum()), int(has.sum())
                counts[name][0] += hits
                counts[name][1] += beams_here
                value = hits / beams_here if beams_here else None
            out[name][beam_type] = value
    for name, (hits, total) in counts.items():
        out[name]["pooled"] = hits / total if total else None
    return out


MAE_KEYS = {
    "model": "mae_db",
    "oracle": "oracle_mae_db",
    "noise_floor": "noise_floor_mae_db",
    "trivial": "trivial_mae_db",
    "bias": "bias_db",
}
"""Each :func:`_mae_triplet` entry's key in the metrics."""


def _mae_blocks(
    beams: dict[str, BeamResult], any_changed: bool, seen_only: bool = False
) -> dict[str, dict[str, dict[str, float | None]]]:
    """``{mae_db|oracle_mae_db|trivial_mae_db|noise_floor_mae_db|bias_db: {ssb|csi: {all, changed}}}`` over every
    scored row (only those with training data when ``seen_only``)."""
    blocks = _split_blocks(beams, any_changed, _mae_triplet, tuple(MAE_KEYS), seen_only)
    return {MAE_KEYS[k]: block for k, block in blocks.items()}


def _split_blocks(
    beams: dict[str, BeamResult],
    any_changed: bool,
    score: Callable[[BeamResult, np.ndarray], dict[str, float | None]],
    keys: tuple[str, ...],
    seen_only: bool = False,
) -> dict[str, dict[str, dict[str, float | None]]]:
    """``{key: {ssb|csi: {all, changed}}}`` of ``score`` over every scored row (only those with training data when
    ``seen_only``) and over the changed cells' rows."""
    out: dict[str, dict[str, dict[str, float | None]]] = {k: {} for k in keys}
    for beam_type, res in beams.items():
        rows = res.rows() & res.seen if seen_only else res.rows()
        every = score(res, rows)
        changed = score(res, rows & res.changed) if any_changed else dict.fromkeys(every)
        for k in out:
            out[k][beam_type] = {"all": every[k], "changed": changed[k]}
    return out


def _per_cell(beams: dict[str, BeamResult], changed: np.ndarray) -> dict[str, Any]:
    cells = sorted({int(c) for res in beams.values() for c in res.pairs["cell_id"].to_numpy()})
    # each source's errors once per beam type, then per cell only its rows (issue 29: per cell over every pair took
    # 53 of 283 s of `evaluate` at 222 cells); the same entries as _mae_triplet gives
    errors = {
        beam_type: {
            name: None if values is None else M.abs_error_db(values, res.measured)
            for name, values in (
                ("model", res.model),
                ("oracle", res.oracle),
                ("trivial", res.trivial),
                ("noise_floor", res.noiseless),
            )
        }
        for beam_type, res in beams.items()
    }
    changed_set = set(changed.tolist())
    out: dict[str, Any] = {}
    for cell in cells:
        entry: dict[str, Any] = {
            "changed": bool(cell in changed_set),
            "oracle": {},
            "trivial": {},
            "noise_floor": {},
            "counts": {},
        }
        for beam_type, res in beams.items():
            rows = res.rows() & (res.pairs["cell_id"].to_numpy() == cell)
            err = errors[beam_type]
            trip = {name: None if e is None else M.mae_db(e, rows) for name, e in err.items()}
            entry[beam_type] = trip["model"]
            entry["oracle"][beam_type] = trip["oracle"]
            entry["trivial"][beam_type] = trip["trivial"]
            entry["noise_floor"][beam_type] = trip["noise_floor"]
            entry["counts"][beam_type] = M.count_finite(err["model"], rows)  # type: ignore[arg-type]
        out[str(cell)] = entry
    return out


def _seen_block(beams: dict[str, BeamResult], any_changed: bool) -> dict[str, Any]:
    """The MAE blocks of :func:`_mae_blocks` over the scored pairs that had training data, and their number."""
    pairs = {bt: int((res.rows() & res.seen).sum()) for bt, res in beams.items()}
    return {**_mae_blocks(beams, any_changed, seen_only=True), "pairs": pairs}


def _unseen_block(model: APSSource, beams: dict[str, BeamResult]) -> dict[str, Any]:
    block: dict[str, Any] = {
        "mae_db": {},
        "oracle_mae_db": {},
        "trivial_mae_db": {},
        "noise_floor_mae_db": {},
        "bias_db": {},
        "pairs": {},
    }
    for beam_type, res in beams.items():
        rows = ~res.seen
        trip = (
            _mae_triplet(res, rows)
            if rows.any()
            else dict.fromkeys(("model", "oracle", "trivial", "noise_floor", "bias"))
        )
        block["mae_db"][beam_type] = trip["model"] if model.supports_unseen_grids else None
        block["bias_db"][beam_type] = trip["bias"] if model.supports_unseen_grids else None
        block["oracle_mae_db"][beam_type] = trip["oracle"]
        block["trivial_mae_db"][beam_type] = trip["trivial"]
        block["noise_floor_mae_db"][beam_type] = trip["noise_floor"]
        block["pairs"][beam_type] = int(rows.sum())
    return block


def _aps_metrics(
    model: APSSource,
    oracle: APSSource | None,
    beams: dict[str, BeamResult],
    evaluation: Evaluation,
    top_k: int,
    max_pairs: int,
) -> dict[str, Any]:
    """APS recovery against the oracle's (true) APS over a seeded subsample of the scored test pairs."""
    out: dict[str, Any] = {"nmse_db": None, "nmse_db_median": None, "angle_error_deg": None, "top_k": top_k, "pairs": 0}
    if oracle is None:
        return out
    pairs = _aps_sample([res.pairs[res.scored] for res in beams.values()], max_pairs)
    if pairs is None:
        return out
    cells, grids = pairs["cell_id"].to_numpy(), pairs["grid_id"].to_numpy()
    try:
        est = np.concatenate(
            [_aps_chunk(model, cells[s : s + 256], grids[s : s + 256]) for s in range(0, len(pairs), 256)]
        )
        true = np.concatenate(
            [_aps_chunk(oracle, cells[s : s + 256], grids[s : s + 256]) for s in range(0, len(pairs), 256)]
        )
    except UnsupportedError:
        return out
    nmse_db = M.aps_nmse_db(est, true)
    angle = M.aps_angle_error_deg(est, true, model.angle_grid, top_k)
    finite = nmse_db[np.isfinite(nmse_db)]
    out.update(
        nmse_db=M.nanmean_or_none(nmse_db),
        nmse_db_median=float(np.median(finite)) if len(finite) else None,
        angle_error_deg=M.nanmean_or_none(angle),
        pairs=int(len(pairs)),
    )
    evaluation.aps_pairs, evaluation.aps_est, evaluation.aps_true = (
        pairs,
        est.astype(np.float32),
        true.astype(np.float32),
    )
    return out


def _aps_sample(frames: list[pd.DataFrame], max_pairs: int) -> pd.DataFrame | None:
    """The distinct (cell, grid) pairs of ``frames`` the APS metrics use, sorted: all, or a seeded subsample of
    ``max_pairs``; None when there are none."""
    if not frames or max_pairs <= 0:
        return None
    pairs = pd.concat(frames)[["cell_id", "grid_id"]].drop_duplicates()
    pairs = pairs.sort_values(["cell_id", "grid_id"], ignore_index=True)
    if not len(pairs):
        return None
    if len(pairs) > max_pairs:
        pick = np.sort(np.random.default_rng(0).choice(len(pairs), max_pairs, replace=False))
        pairs = pairs.iloc[pick].reset_index(drop=True)
    return pairs


def _aps_chunk(model: APSSource, cells: np.ndarray, grids: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return checked_aps(model, cells, grids).detach().float().cpu().numpy()


def _counts(beams: dict[str, BeamResult], changed: np.ndarray) -> dict[str, Any]:
    counts: dict[str, Any] = {}
    for beam_type, res in beams.items():
        err = M.abs_error_db(res.model, res.measured)
        counts[beam_type] = {
            "test_pairs": int(len(res.pairs)),
            "scored_pairs": int(res.scored.sum()),
            "beams": M.count_finite(err, res.scored),
            "changed_beams": M.count_finite(err, res.scored & res.changed),
        }
    cells = {int(c) for res in beams.values() for c in res.pairs["cell_id"].to_numpy()}
    counts["cells"] = len(cells)
    counts["changed_cells"] = [int(c) for c in changed]
    return counts


def _assemble(
    model: APSSource,
    scenario: Scenario,
    protocol: Protocol,
    test_round: int,
    beams: dict[str, BeamResult],
    changed: np.ndarray,
    aps: dict[str, Any],
    unsupported: str | None,
    timing: dict[str, float],
) -> dict[str, Any]:
    return {
        **_mae_blocks(beams, any_changed=len(changed) > 0),
        "missing_above_bound": _above_bound(beams),
        "truth_mae_db": _truth_block(beams, any_changed=len(changed) > 0),
        "per_cell": _per_cell(beams, changed),
        "aps": aps,
        "unseen": _unseen_block(model, beams),
        "seen": _seen_block(beams, any_changed=len(changed) > 0),
        "counts": _counts(beams, changed),
        "model": {
            "name": model.name,
            "supports_unseen_grids": bool(model.supports_unseen_grids),
            "fingerprint": model.fingerprint,
            "fit": model.run_info.get("fit"),
        },
        "protocol": protocol_to_dict(protocol),
        "test_round": int(test_round),
        "scenario": {"name": scenario.meta.name, "root": str(scenario.root)},
        "unsupported": unsupported,
        "timing_s": {k: round(v, 3) for k, v in timing.items()},
    }
