"""Protocols: what each trains on and tests on, seeded splits, serialisation, and split checks."""

from __future__ import annotations

import numpy as np
import pytest

from rflscm.errors import ConfigError, DataError
from rflscm.eval import (
    AdjustProtocol,
    MultiFreqProtocol,
    UnseenProtocol,
    fit_with_protocol,
    make_protocol,
    protocol_from_dict,
    protocol_to_dict,
    resolve_protocol,
    split_grids,
)
from rflscm.geometry import AngleGrid
from rflscm.models import MODEL_REGISTRY


def _pairs(scenario, rnd: int) -> set[tuple[int, int]]:
    m = scenario.measurements
    rows = m[(m["round"] == rnd) & m["rsrp_dbm"].notna()]
    return set(zip(rows["cell_id"], rows["grid_id"]))


def test_adjust_trains_on_round_1_and_tests_on_round_2(sim_scenario) -> None:
    protocol = AdjustProtocol()
    train = protocol.training_scenario(sim_scenario)
    assert set(train.measurements["round"]) == {1}
    assert _pairs(train, 1) == _pairs(sim_scenario, 1)
    test = protocol.test_set(sim_scenario)
    assert test.round == 2
    pairs, rsrp = test.tables["ssb"]
    assert len(pairs) and np.isfinite(rsrp).any(1).all()
    assert set(zip(pairs["cell_id"], pairs["grid_id"])) <= _pairs(sim_scenario, 2)
    with pytest.raises(DataError, match="round 3"):
        AdjustProtocol(test_round=3).test_set(sim_scenario)
    # the distinct pairs over both beam types (CSI-RS is reported on fewer pairs than SSB, never on others)
    both = test.pairs()
    assert set(zip(both["cell_id"], both["grid_id"])) == _pairs(sim_scenario, 2) and not both.duplicated().any()


def test_unseen_holds_out_whole_grids(sim_scenario) -> None:
    held = split_grids(sim_scenario, 0.1, seed=0)
    measured = np.unique(sim_scenario.measurements.query("round == 1 and rsrp_dbm == rsrp_dbm")["grid_id"])
    assert len(held) == round(0.1 * len(measured)) and set(held) <= set(measured)
    assert np.array_equal(held, split_grids(sim_scenario, 0.1, seed=0))  # repeatable
    assert not np.array_equal(held, split_grids(sim_scenario, 0.1, seed=1))
    protocol = UnseenProtocol(fraction=0.1, seed=0)
    train = protocol.training_scenario(sim_scenario)
    assert not set(train.measurements["grid_id"]) & set(held)
    assert set(train.measurements["round"]) == {1}
    test = protocol.test_set(sim_scenario)
    assert test.round == 1
    for pairs, _ in test.tables.values():
        assert set(pairs["grid_id"]) <= set(held) and len(pairs)


def test_multifreq_split(sim_scenario) -> None:
    protocol = MultiFreqProtocol(train_percent=10.0, with_other_carriers=True, seed=0)
    assert protocol.carrier(sim_scenario) == 2.1e9  # the lowest carrier by default
    cells, train_grids, test_grids = protocol.split(sim_scenario)
    assert not set(train_grids) & set(test_grids)
    low = sim_scenario.measurements.query("round == 1 and rsrp_dbm == rsrp_dbm and cell_id in @cells")
    num = low["grid_id"].nunique()
    assert len(test_grids) == round(0.7 * num) and len(train_grids) == max(1, round(0.1 * num))
    bigger = MultiFreqProtocol(train_percent=30.0, seed=0).split(sim_scenario)[1]
    assert set(train_grids) <= set(bigger)  # nested draws for a p sweep
    train = protocol.training_scenario(sim_scenario).measurements
    on_low = train["cell_id"].isin(cells)
    assert set(train.loc[on_low, "grid_id"]) <= set(train_grids)
    all_high = sim_scenario.measurements.query("round == 1 and cell_id not in @cells")
    assert (~on_low).sum() == len(all_high)  # every row of the other carrier
    alone = MultiFreqProtocol(train_percent=10.0, with_other_carriers=False).training_scenario(sim_scenario)
    assert alone.measurements["cell_id"].isin(cells).all()
    for pairs, _ in protocol.test_set(sim_scenario).tables.values():
        assert set(pairs["cell_id"]) <= set(cells) and set(pairs["grid_id"]) <= set(test_grids)


def test_protocol_settings_are_checked_and_round_trip() -> None:
    for protocol in (AdjustProtocol(), UnseenProtocol(fraction=0.2, seed=3), MultiFreqProtocol(train_percent=5.0)):
        assert protocol_from_dict(protocol_to_dict(protocol)) == protocol
    assert make_protocol("unseen", fraction=0.25) == UnseenProtocol(fraction=0.25)
    with pytest.raises(ConfigError, match="choose one of: adjust, unseen, multifreq"):
        make_protocol("crossval")
    with pytest.raises(ConfigError, match="valid keys"):
        make_protocol("unseen", fractoin=0.2)
    with pytest.raises(ConfigError, match=r"train_percent` must lie in \(0, 30\]"):
        MultiFreqProtocol(train_percent=50.0)
    with pytest.raises(ConfigError, match="fraction"):
        UnseenProtocol(fraction=1.0)


def test_training_records_the_split_and_evaluation_insists_on_it(sim_scenario) -> None:
    model = MODEL_REGISTRY["wnomp"].build(None, AngleGrid(31, 36, -90.0, 6.0), "cpu")
    fit_with_protocol(model, sim_scenario, UnseenProtocol(fraction=0.2, seed=5), progress=False)
    assert model.run_info["protocol"] == {"name": "unseen", "fraction": 0.2, "seed": 5}
    assert model.fingerprint == sim_scenario.fingerprint()  # of the full scenario, not the split
    held = split_grids(sim_scenario, 0.2, seed=5)
    assert not set(model.grid_ids) & set(held)
    assert resolve_protocol(model, None) == UnseenProtocol(fraction=0.2, seed=5)
    assert resolve_protocol(model, "unseen") == UnseenProtocol(fraction=0.2, seed=5)
    with pytest.raises(ConfigError, match="trained for the 'unseen' protocol"):
        resolve_protocol(model, "adjust")
    with pytest.raises(ConfigError, match="differ from the training split"):
        resolve_protocol(model, UnseenProtocol(fraction=0.1))
    model.run_info.pop("protocol")
    assert resolve_protocol(model, None) == AdjustProtocol()
    with pytest.raises(ConfigError, match="does not record its training split"):
        resolve_protocol(model, "multifreq")
