"""Evaluation protocols (SPEC §5, paper §V): which data a model trains on and what it is tested on.

Each protocol is a frozen dataclass with

* ``training_scenario(scenario) -> Scenario``: the same scenario with a filtered measurement table
  (round 1 only, minus the held-out rows), so that models never know about splits;
* ``test_set(scenario) -> TestSet``: the test round and, per beam type, the (cell, grid) pairs with
  their measured RSRP [dBm].

Splits are seeded and depend only on the scenario's grid ids, so training and evaluation (which
may run in different processes) agree.  Training stores the protocol in
``model.run_info["protocol"]`` (:func:`fit_with_protocol`) and evaluation reads it back
(:func:`protocol_from_dict`).

=============  =========================================================================================
protocol       train → test
=============  =========================================================================================
``adjust``     all round-1 measurements → round 2 (the changed antenna configuration, predicted with A′)
``unseen``     round 1 without a seeded ``fraction`` of grids → those grids' round-1 RSRP
``multifreq``  ``train_percent`` % of the lowest carrier's grids (drawn from the 30 % not in the fixed
               70 % test set), plus all other carriers' data if ``with_other_carriers`` → the test set's
               round-1 RSRP on the lowest carrier
=============  =========================================================================================
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import pandas as pd

from rflscm.config import from_dict, to_dict
from rflscm.data import BEAM_TYPES
from rflscm.data.measurements import select_rows
from rflscm.errors import ConfigError, DataError
from rflscm.train import fit

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.models.base import LSCMModel


@dataclass
class TestSet:
    """What a protocol tests: measured RSRP of one round.

    Attributes:
        round: the measurement round whose antenna configuration the predictions use.
        tables: beam type → ``(pairs, rsrp_dbm)``; ``pairs`` (``cell_id``, ``grid_id``) and
            ``rsrp_dbm [num_pairs, max_beams]`` [dBm], NaN = not reported; only pairs with at least
            one reported beam.
    """

    round: int
    tables: dict[str, tuple[pd.DataFrame, np.ndarray]]

    def pairs(self) -> pd.DataFrame:
        """The distinct (``cell_id``, ``grid_id``) pairs tested, over every beam type."""
        both = pd.concat([pairs[["cell_id", "grid_id"]] for pairs, _ in self.tables.values()], ignore_index=True)
        return both.drop_duplicates(ignore_index=True)


def _round1_rows(scenario: Scenario) -> pd.DataFrame:
    m = scenario.measurements
    return select_rows(m, (m["round"] == 1).to_numpy())


def _measured_grids(rows: pd.DataFrame) -> np.ndarray:
    """Sorted grid ids with at least one reported RSRP in ``rows``."""
    return np.unique(rows.loc[rows["rsrp_dbm"].notna().to_numpy(), "grid_id"].to_numpy(np.int64))


def _test_tables(
    scenario: Scenario, round: int, keep: Callable[[pd.DataFrame], np.ndarray] | None = None
) -> dict[str, tuple[pd.DataFrame, np.ndarray]]:
    """Per beam type, the pairs of ``round`` (filtered by ``keep(pairs) -> bool mask``) with a reported beam."""
    tables = {}
    for beam_type in BEAM_TYPES:
        pairs, rsrp = scenario.rsrp_table(round, beam_type)
        mask = np.isfinite(rsrp).any(1) if rsrp.size else np.zeros(len(pairs), dtype=bool)
        if keep is not None:
            mask &= keep(pairs)
        tables[beam_type] = (pairs[mask].reset_index(drop=True), rsrp[mask])
    return tables


@dataclass(frozen=True)
class AdjustProtocol:
    """Antenna-adjustment test: train on all round-1 data, predict round ``test_round`` with its A′."""

    name: Literal["adjust"] = "adjust"
    test_round: int = 2

    def training_scenario(self, scenario: Scenario) -> Scenario:
        return scenario.with_measurements(_round1_rows(scenario), validate=False)

    def test_set(self, scenario: Scenario) -> TestSet:
        if self.test_round not in scenario.cells:
            raise DataError(
                f"the adjust protocol tests on round {self.test_round}, but scenario {scenario.meta.name!r} has rounds "
                f"{', '.join(map(str, scenario.rounds()))}; use --protocol unseen for a single-round scenario."
            )
        tables = _test_tables(scenario, self.test_round)
        if not any(len(p) for p, _ in tables.values()):
            raise DataError(f"scenario {scenario.meta.name!r} has no round-{self.test_round} measurements to test on.")
        return TestSet(self.test_round, tables)


def split_grids(scenario: Scenario, fraction: float, seed: int) -> np.ndarray:
    """A seeded ``fraction`` of the grids measured in round 1 (sorted ids), at least one when fraction > 0."""
    grids = _measured_grids(_round1_rows(scenario))
    num = int(round(fraction * len(grids)))
    num = max(num, 1) if fraction > 0 and len(grids) > 1 else num
    num = min(num, len(grids) - 1)  # always leave something to train on
    held = np.random.default_rng(seed).permutation(grids)[: max(num, 0)]
    return np.sort(held)


@dataclass(frozen=True)
class UnseenProtocol:
    """Unseen grids: hold out a seeded ``fraction`` of the measured grids entirely; test on their round-1 RSRP."""

    name: Literal["unseen"] = "unseen"
    fraction: float = 0.1
    seed: int = 0

    def __post_init__(self) -> None:
        if not 0.0 < self.fraction < 1.0:
            raise ConfigError(f"`protocol.fraction` must lie in (0, 1) (got {self.fraction}).")

    def held_out(self, scenario: Scenario) -> np.ndarray:
        return split_grids(scenario, self.fraction, self.seed)

    def training_scenario(self, scenario: Scenario) -> Scenario:
        rows = _round1_rows(scenario)
        keep = ~rows["grid_id"].isin(self.held_out(scenario)).to_numpy()
        return scenario.with_measurements(select_rows(rows, keep), validate=False)

    def test_set(self, scenario: Scenario) -> TestSet:
        held = self.held_out(scenario)
        return TestSet(1, _test_tables(scenario, 1, lambda pairs: pairs["grid_id"].isin(held).to_numpy()))


@dataclass(frozen=True)
class MultiFreqProtocol:
    """Multi-frequency test (paper §V-C).

    The fixed test set is ``test_fraction`` of the grids measured on the lowest carrier (or
    ``carrier_hz``); the model trains on ``train_percent`` % of *all* that carrier's grids, drawn from
    the rest (so 30 = the whole remaining pool with the default 70 % test), plus every measurement of
    the other carriers when ``with_other_carriers``.  Draws are nested: a smaller ``train_percent``
    takes a prefix of the same seeded order.
    """

    name: Literal["multifreq"] = "multifreq"
    train_percent: float = 10.0
    with_other_carriers: bool = True
    test_fraction: float = 0.7
    seed: int = 0
    carrier_hz: float | None = None

    def __post_init__(self) -> None:
        if not 0.0 < self.test_fraction < 1.0:
            raise ConfigError(f"`protocol.test_fraction` must lie in (0, 1) (got {self.test_fraction}).")
        pool = 100.0 * (1.0 - self.test_fraction)
        if not 0.0 < self.train_percent <= pool + 1e-9:
            raise ConfigError(
                f"`protocol.train_percent` must lie in (0, {pool:g}] (the grids outside the {100 * self.test_fraction:g} % "
                f"test set; got {self.train_percent})."
            )

    def carrier(self, scenario: Scenario) -> float:
        freqs = np.unique(scenario.cells[1]["freq_hz"].to_numpy(np.float64))
        if len(freqs) < 2:
            raise DataError(
                f"the multifreq protocol needs cells on at least two carriers; scenario {scenario.meta.name!r} has only "
                f"{freqs[0] / 1e9:g} GHz."
            )
        if self.carrier_hz is None:
            return float(freqs[0])
        if not np.isclose(freqs, self.carrier_hz).any():
            listed = ", ".join(f"{f:g}" for f in freqs)
            raise ConfigError(
                f"`protocol.carrier_hz` = {self.carrier_hz:g} is not a carrier of the scenario ({listed})."
            )
        return float(freqs[np.isclose(freqs, self.carrier_hz)][0])

    def split(self, scenario: Scenario) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(carrier_cells, train_grids, test_grids)`` (sorted ids)."""
        cells = scenario.cells[1]
        on_carrier = cells.loc[np.isclose(cells["freq_hz"].to_numpy(np.float64), self.carrier(scenario)), "cell_id"]
        carrier_cells = np.sort(on_carrier.to_numpy(np.int64))
        rows = _round1_rows(scenario)
        grids = _measured_grids(rows[rows["cell_id"].isin(carrier_cells).to_numpy()])
        order = np.random.default_rng(self.seed).permutation(grids)
        num_test = int(round(self.test_fraction * len(grids)))
        num_train = max(1, int(round(self.train_percent / 100.0 * len(grids))))
        test, pool = order[:num_test], order[num_test:]
        return carrier_cells, np.sort(pool[:num_train]), np.sort(test)

    def training_scenario(self, scenario: Scenario) -> Scenario:
        carrier_cells, train, _ = self.split(scenario)
        rows = _round1_rows(scenario)
        on = rows["cell_id"].isin(carrier_cells).to_numpy()
        keep = on & rows["grid_id"].isin(train).to_numpy()
        if self.with_other_carriers:
            keep |= ~on
        return scenario.with_measurements(rows[keep], validate=False)

    def test_set(self, scenario: Scenario) -> TestSet:
        carrier_cells, _, test = self.split(scenario)

        def keep(pairs: pd.DataFrame) -> np.ndarray:
            return (pairs["cell_id"].isin(carrier_cells) & pairs["grid_id"].isin(test)).to_numpy()

        return TestSet(1, _test_tables(scenario, 1, keep))


Protocol = AdjustProtocol | UnseenProtocol | MultiFreqProtocol
PROTOCOLS: dict[str, type] = {"adjust": AdjustProtocol, "unseen": UnseenProtocol, "multifreq": MultiFreqProtocol}


def make_protocol(name: str, **settings: object) -> Protocol:
    """A protocol by name with optional settings (e.g. ``make_protocol("unseen", fraction=0.2)``)."""
    if name not in PROTOCOLS:
        raise ConfigError(f"unknown protocol {name!r}; choose one of: {', '.join(PROTOCOLS)}.")
    return from_dict(PROTOCOLS[name], settings, prefix="protocol")


def protocol_to_dict(protocol: Protocol) -> dict[str, Any]:
    """Plain mapping (with ``name``) for ``run_info`` and JSON."""
    return to_dict(protocol)


def protocol_from_dict(data: dict[str, Any]) -> Protocol:
    """Inverse of :func:`protocol_to_dict`."""
    if not isinstance(data, dict) or data.get("name") not in PROTOCOLS:
        raise ConfigError(f"`protocol` must be a mapping whose `name` is one of {', '.join(PROTOCOLS)} (got {data!r}).")
    return from_dict(PROTOCOLS[data["name"]], data, prefix="protocol")


def fit_with_protocol(
    model: LSCMModel,
    scenario: Scenario,
    protocol: Protocol | None = None,
    budget_s: float | None = None,
    **fit_kwargs: Any,
) -> dict[str, float]:
    """Fit ``model`` on ``protocol.training_scenario(scenario)`` and record the split.

    Sets ``model.fingerprint`` to the *full* scenario's (so that ``load_model(ckpt, scenario)``
    accepts the scenario the split was drawn from; :func:`rflscm.train.fit` keeps it) and
    ``model.run_info["protocol"]``, then calls :func:`rflscm.train.fit` with ``budget_s`` (a wall-time
    training budget [s], None: ``train.steps`` steps) and ``fit_kwargs`` (``progress``, ``checkpoint_path``, …).
    """
    protocol = protocol or AdjustProtocol()
    model.fingerprint = scenario.fingerprint()
    model.run_info["protocol"] = protocol_to_dict(protocol)
    return fit(model, protocol.training_scenario(scenario), budget_s=budget_s, **fit_kwargs)
