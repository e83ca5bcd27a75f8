"""Search specs: defaults, the current value always an option, and one clear error per bad spec."""

from __future__ import annotations

from pathlib import Path

import pytest
from network_helpers import load, pencil_scenario

from rflscm.errors import ConfigError
from rflscm.network.space import VARIABLES, build_space, parse_range


@pytest.fixture
def scen(tmp_path: Path):
    return load(pencil_scenario(tmp_path / "pencil"))


def test_defaults_are_a_planners(scen) -> None:
    space = build_space({}, scen.cells[1], scen.meta.codebooks)
    cell12 = space.cells[1]
    assert cell12.values["mech_tilt_deg"] == tuple(float(v) for v in range(16))
    assert len(cell12.values["azimuth_deg"]) == 13 and cell12.values["azimuth_deg"][0] == 150.0
    assert set(cell12.values["ssb_codebook"]) == {"ssb8", "pencil"}
    assert cell12.config(cell12.current) == {v: scen.cells[1].iloc[1][v] for v in VARIABLES}


def test_any_named_codebook_may_serve_ssb(scen) -> None:
    # issue 25: any codebook kind may serve SSB, so a DFT book is a valid choice when named
    space = build_space({"defaults": {"ssb_codebooks": ["csi8"]}}, scen.cells[1], scen.meta.codebooks)
    assert "csi8" in space.cells[1].values["ssb_codebook"]


@pytest.mark.parametrize(
    ("spec", "match"),
    [
        ({"defaults": {"mech_tilt_deg": {"min": 10, "max": 2}}}, "range reversed"),
        ({"frozen": [99]}, "unknown cell 99"),
        ({"cells": {12: {"ssb_codebooks": ["nope"]}}}, "'nope' is not a codebook of scenario.yaml"),
        ({"frozen": [11, 12]}, "empty search space"),
        (
            {"defaults": {"mech_tilt_deg": {"min": 0, "max": 5, "step": 0}}},
            "step must be > 0",
        ),
        ({"bogus": 1}, "unknown key"),
        ({"max_changed_cells": 0}, "max_changed_cells"),
    ],
)
def test_bad_specs(scen, spec: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        build_space(spec, scen.cells[1], scen.meta.codebooks)


def test_empty_when_every_range_is_the_current_value(scen) -> None:
    fixed = {"min": 4, "max": 4}
    spec = {"cells": {11: {"mech_tilt_deg": {"min": 4, "max": 4}, "elec_tilt_deg": {"min": 0, "max": 0},
                           "azimuth_offset_deg": {"min": 0, "max": 0}, "ssb_codebooks": ["pencil"]},
                      12: {"mech_tilt_deg": {"min": 2, "max": 2}, "elec_tilt_deg": fixed,
                           "azimuth_offset_deg": {"min": 0, "max": 0}, "ssb_codebooks": ["ssb8"]}}}  # fmt: skip
    with pytest.raises(ConfigError, match="empty search space"):
        build_space(spec, scen.cells[1], scen.meta.codebooks)


def test_parse_range() -> None:
    assert parse_range("0:15:1", "--tilt-range") == {
        "min": 0.0,
        "max": 15.0,
        "step": 1.0,
    }
    with pytest.raises(ConfigError, match="MIN:MAX"):
        parse_range("0-15", "--tilt-range")
