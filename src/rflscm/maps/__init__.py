"""Maps a GIS opens: GeoTIFF rasters, GeoJSON and KML of grids, cells and measured points, and an offline
interactive HTML map, of a trained model's predicted KPIs (docs/maps.md).

Sits above :mod:`rflscm.eval` and :mod:`rflscm.network`: it predicts through their code and draws.
"""

from rflscm.maps.crs import NOMINAL_ORIGIN, MapFrame
from rflscm.maps.layers import CarrierLayer, RoundLayers, map_pairs, round_layers
from rflscm.maps.raster import Lattice
from rflscm.maps.write import MapOutputs, write_layers

__all__ = [
    "NOMINAL_ORIGIN",
    "CarrierLayer",
    "Lattice",
    "MapFrame",
    "MapOutputs",
    "RoundLayers",
    "map_pairs",
    "round_layers",
    "write_layers",
]
