"""The contract between a propagation backend and the scenario builder.

A backend knows a scene (buildings and ground) and traces propagation paths
from a transmitter point to receiver points with an *isotropic* antenna at both
ends.  Everything antenna-specific (element pattern, beams, rotations) is
applied afterwards from the path table, so one trace serves every antenna
configuration (SPEC §6).

Path table (``pandas.DataFrame``), one row per propagation path:

==================  =======  ===================================================
column              dtype    meaning
==================  =======  ===================================================
``rx_index``        int64    index into the receiver points passed to ``trace``
``power_lin``       float64  path power gain |a|^2 (isotropic antennas) [linear]
``aod_el_rad``      float64  angle of departure, elevation above horizon [rad]
``aod_az_rad``      float64  angle of departure, azimuth CCW from east [rad]
``delay_s``         float64  propagation delay [s]
``interactions``    string   interaction types in order: "LOS", or letters
                             R (specular reflection), D (diffraction),
                             S (diffuse scattering), T (transmission / penetration)
==================  =======  ===================================================

Angles are in the world ENU frame (x east, y north, z up) of the scene, the
code-internal convention of :mod:`rflscm.geometry.angles`.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
import pandas as pd

PATH_COLUMNS: dict[str, str] = {
    "rx_index": "int64",
    "power_lin": "float64",
    "aod_el_rad": "float64",
    "aod_az_rad": "float64",
    "delay_s": "float64",
    "interactions": "string",
}


def empty_path_table() -> pd.DataFrame:
    """A path table with the right columns and no rows."""
    return pd.DataFrame({c: pd.Series(dtype=t) for c, t in PATH_COLUMNS.items()})


@runtime_checkable
class SceneBackend(Protocol):
    """A scene plus a propagation engine.

    All coordinates are metres in the scene's ENU frame.
    """

    name: str

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Axis-aligned box ``(lo[3], hi[3])`` holding buildings and ground [m]."""
        ...

    def rooftops(self) -> np.ndarray:
        """Candidate site positions on building roofs, ``[num_candidates, 3]``:
        x, y of a point well inside a roof and z = roof height [m]."""
        ...

    def ground_height(self, xy: np.ndarray) -> np.ndarray:
        """Ground height ``[num_points]`` at ``xy`` ``[num_points, 2]`` [m]."""
        ...

    def is_outdoor(self, xy: np.ndarray) -> np.ndarray:
        """Boolean ``[num_points]``: True where ``xy`` is not inside a building."""
        ...

    def sample_point_cloud(self, points_per_m2: float, noise_std_m: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """A LiDAR-like scan of the scene surfaces.

        Returns ``(xyz [num_points, 3] float64, classification [num_points] uint8)``
        with ASPRS classes 2 (ground) and 6 (building).
        """
        ...

    def trace(self, tx_position: np.ndarray, rx_positions: np.ndarray, freq_hz: float, seed: int) -> pd.DataFrame:
        """Trace paths from ``tx_position[3]`` to every row of ``rx_positions[num_rx, 3]``
        at carrier ``freq_hz`` [Hz]; returns a path table (see module docstring)."""
        ...
