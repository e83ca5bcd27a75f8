"""Search specs: defaults, the current value always an option, and one clear error per bad spec."""

from __future__ import annotations

from pathlib import Path

import pytest
from network_helpers import load, pencil_scenario

from rflscm.errors import ConfigError
from rflscm.network.space import (
    DEFAULT_MAX_CHANGED,
    PHYSICAL_LIMITS,
    VARIABLES,
    build_space,
    panel_groups,
    parse_range,
)


@pytest.fixture
def scen(tmp_path: Path):
    return load(pencil_scenario(tmp_path / "pencil"))


def test_defaults_are_a_planners(scen) -> None:
    space = build_space({}, scen.cells[1], scen.meta.codebooks)
    cell12 = space.cells[1]  # mech 2°, elec 4°, azimuth 180°
    # the 0…15° range, cut to the default step of ±4° around the present value
    assert cell12.values["mech_tilt_deg"] == tuple(float(v) for v in range(0, 7))
    assert cell12.values["elec_tilt_deg"] == tuple(float(v) for v in range(0, 9))
    assert cell12.values["azimuth_deg"] == (170.0, 175.0, 180.0, 185.0, 190.0)  # ±10°, not ±30°
    assert set(cell12.values["ssb_codebook"]) == {"ssb8", "pencil"}
    assert cell12.config(cell12.current) == {v: scen.cells[1].iloc[1][v] for v in VARIABLES}
    assert space.max_changed_cells == DEFAULT_MAX_CHANGED and space.max_total_tilt_step == 4.0
    # total tilt: +3° mechanical and +3° electrical is 6° of total down-tilt, beyond the 4° step
    opts = cell12.values
    up3 = (cell12.current[0], opts["elec_tilt_deg"].index(7.0), opts["mech_tilt_deg"].index(5.0), cell12.current[3])
    assert not space.tilt_ok(1, up3)
    swap = (cell12.current[0], opts["elec_tilt_deg"].index(1.0), opts["mech_tilt_deg"].index(5.0), cell12.current[3])
    assert space.tilt_ok(1, swap)


@pytest.mark.parametrize(
    ("key", "bounds"),
    [("mech_tilt_deg", (0, 40)), ("elec_tilt_deg", (-10, 10)), ("azimuth_offset_deg", (-90, 90))],
)
def test_ranges_beyond_physical_limits_are_refused(scen, key: str, bounds: tuple[int, int]) -> None:
    spec = {"defaults": {key: {"min": bounds[0], "max": bounds[1], "step": 1}}}
    lo, hi = PHYSICAL_LIMITS[key]
    with pytest.raises(ConfigError, match=f"physical limits {lo:g}…{hi:g} degrees"):
        build_space(spec, scen.cells[1], scen.meta.codebooks)


def _co_sited(scen, panel_ids: list | None = None):
    cells = scen.cells[1].copy()
    cells["azimuth_deg"] = 60.0  # cells 11 (3.5 GHz) and 12 (2.1 GHz) of site 1 on one panel
    if panel_ids is not None:
        cells["panel_id"] = panel_ids
    return cells


def test_co_sited_cells_with_one_azimuth_share_a_panel(scen) -> None:
    assert panel_groups(scen.cells[1]) == ()  # 60° and 180°: two panels
    assert panel_groups(_co_sited(scen)) == ((0, 1),)
    assert panel_groups(_co_sited(scen, ["a", "b"])) == ()  # declared: separate panels
    assert panel_groups(_co_sited(scen, ["p", "p"])) == ((0, 1),)
    space = build_space({}, _co_sited(scen), scen.meta.codebooks)
    # cell 11 turned by +10° and 1° more mechanical tilt: cell 12 follows on both, keeps its electrical tilt
    a = space.cells[0]
    moved = list(a.current)
    moved[3] = a.values["azimuth_deg"].index(70.0)
    moved[2] = a.values["mech_tilt_deg"].index(5.0)
    config = space.tie([tuple(moved), space.cells[1].current])
    got = space.cells[1].config(config[1])
    assert got["azimuth_deg"] == 70.0 and got["mech_tilt_deg"] == 3.0 and got["elec_tilt_deg"] == 4.0


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
    spec = {
        "cells": {
            11: {
                "mech_tilt_deg": {"min": 4, "max": 4},
                "elec_tilt_deg": {"min": 0, "max": 0},
                "azimuth_offset_deg": {"min": 0, "max": 0},
                "ssb_codebooks": ["pencil"],
            },
            12: {
                "mech_tilt_deg": {"min": 2, "max": 2},
                "elec_tilt_deg": fixed,
                "azimuth_offset_deg": {"min": 0, "max": 0},
                "ssb_codebooks": ["ssb8"],
            },
        }
    }
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
