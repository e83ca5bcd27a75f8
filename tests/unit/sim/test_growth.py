"""`simulate --backend procedural --sites N`: a city that grows with N at the default density (N ≤ 7 unchanged)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from rflscm.data import load_scenario
from rflscm.errors import ConfigError
from rflscm.geometry import AngleGrid
from rflscm.sim import ProceduralCity, SimulationConfig, build_scenario
from rflscm.sim.builder import grow_procedural
from rflscm.sim.procedural import grown_scene_options

GRID = AngleGrid(num_el=16, num_az=18, el_min_deg=-90.0, el_step_deg=12.0)


@pytest.mark.parametrize("sites", [1, 3, 7])
def test_up_to_seven_sites_the_config_is_the_default_one(sites: int) -> None:
    config = dataclasses.replace(SimulationConfig(), num_sites=sites)
    assert grow_procedural(config, "city") is config
    assert grown_scene_options("city", sites, 7) == {}
    # the default city itself: what the shipped and test scenarios were made with
    city = ProceduralCity(seed=0)
    assert city.size_m == 400.0 and city.num_buildings <= 40


@pytest.mark.parametrize("sites", [14, 28, 70, 350])
def test_area_buildings_and_grids_grow_linearly_with_the_sites(sites: int) -> None:
    base = SimulationConfig()
    grown = grow_procedural(dataclasses.replace(base, num_sites=sites), "city")
    factor = sites / 7
    size = grown.backend_options["size_m"]
    assert size**2 == pytest.approx(400.0**2 * factor)  # area ∝ sites
    assert grown.backend_options["num_buildings"] == round(40 * factor)
    assert grown.max_grids == round(800 * factor)
    assert grown.site_radius_m == pytest.approx(300.0 * factor**0.5)
    assert grown.site_radius_m > size / 2 * 2**0.5  # every rooftop of the grown city is a site candidate


def test_explicit_choices_win_over_growth() -> None:
    config = SimulationConfig(num_sites=14, max_grids=500, backend_options={"size_m": 300.0})
    grown = grow_procedural(config, "small", scale_grids=False)
    assert grown.max_grids == 500 and grown.backend_options == {"size_m": 300.0, "num_buildings": 20}
    fixed = SimulationConfig(num_sites=14, sites=((0.0, 0.0, 20.0),))
    assert grow_procedural(fixed, "city") is fixed
    with pytest.raises(ConfigError, match="unknown procedural scene"):
        grow_procedural(config, "atlantis")


def test_a_grown_city_simulates_with_cells_and_grids_in_proportion(tmp_path: Path) -> None:
    """The small preset at 7 and 14 sites, one carrier: twice the cells and twice the grids."""
    sizes = {}
    for sites in (7, 14):
        config = SimulationConfig(
            num_sites=sites,
            max_grids=15,
            carriers_hz=(3.5e9,),
            angle_grid=GRID,
            point_cloud_points_per_m2=0.02,
            points_per_grid=1,
            seed=1,
        )
        config = grow_procedural(config, "small")
        city = ProceduralCity.from_scene("small", seed=1, **config.backend_options)
        scenario = load_scenario(build_scenario(city, config, tmp_path / str(sites), progress=False))
        sizes[sites] = (len(scenario.cells[1]), len(scenario.grids), city.size_m)
    assert sizes[7] == (21, 15, 200.0)
    assert sizes[14][:2] == (42, 30) and sizes[14][2] == pytest.approx(200.0 * 2**0.5)
