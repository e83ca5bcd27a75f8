"""Scenarios: tables, point clouds, validation and I/O (SPEC §1, §2).

A scenario is a folder with ``scenario.yaml`` (see :mod:`rflscm.data.meta`),
cells tables per measurement round (:mod:`rflscm.data.cells`), a grids table
(:mod:`rflscm.data.positions`), a long-form measurements table
(:mod:`rflscm.data.measurements`) and an optional point cloud
(:mod:`rflscm.data.pointcloud`).  :func:`load_scenario` validates everything
and returns a :class:`Scenario`.
"""

from rflscm.data.cells import CELL_COLUMNS
from rflscm.data.geo import Origin, enu_to_geodetic, geodetic_to_enu
from rflscm.data.io import read_table, write_table
from rflscm.data.loader import SCENARIO_FILE, load_scenario, save_scenario
from rflscm.data.measurements import BEAM_TYPES, MEASUREMENT_COLUMNS, MEASUREMENT_KEY, empty_measurements
from rflscm.data.meta import RSRP_MAX_DBM, RSRP_MIN_DBM, ScenarioMeta
from rflscm.data.pointcloud import ASPRS_CLASSES, PointCloud, read_point_cloud, write_point_cloud
from rflscm.data.positions import GRID_COLUMNS
from rflscm.data.scenario import Scenario

__all__ = [
    "ASPRS_CLASSES",
    "BEAM_TYPES",
    "CELL_COLUMNS",
    "GRID_COLUMNS",
    "MEASUREMENT_COLUMNS",
    "MEASUREMENT_KEY",
    "RSRP_MAX_DBM",
    "RSRP_MIN_DBM",
    "SCENARIO_FILE",
    "Origin",
    "PointCloud",
    "Scenario",
    "ScenarioMeta",
    "empty_measurements",
    "enu_to_geodetic",
    "geodetic_to_enu",
    "load_scenario",
    "read_point_cloud",
    "read_table",
    "save_scenario",
    "write_point_cloud",
    "write_table",
]
