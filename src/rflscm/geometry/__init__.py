"""Frames, the angle converter and the angular grid."""

from rflscm.geometry.angles import (
    angles_of,
    engineering_to_internal,
    internal_to_engineering,
    rotation_matrix,
    unit_vectors,
)
from rflscm.geometry.grid import AngleGrid, CoarseMapping

__all__ = [
    "AngleGrid",
    "CoarseMapping",
    "angles_of",
    "engineering_to_internal",
    "internal_to_engineering",
    "rotation_matrix",
    "unit_vectors",
]
