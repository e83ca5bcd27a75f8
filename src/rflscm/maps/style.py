"""Colour scales shared by the KML and the HTML map (the same ranges as the PNG maps of :mod:`rflscm.eval.plots`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from matplotlib import colormaps
from matplotlib.colors import to_hex


@dataclass(frozen=True)
class Scale:
    """A continuous colour scale: values clipped to ``[low, high]`` (``unit``), colour map ``cmap``."""

    name: str
    unit: str
    low: float
    high: float
    cmap: str

    def colours(self, values: np.ndarray) -> list[str | None]:
        """``#rrggbb`` per value (None for NaN)."""
        values = np.asarray(values, np.float64)
        t = np.clip((values - self.low) / (self.high - self.low), 0.0, 1.0)
        cmap = colormaps[self.cmap]
        return [None if np.isnan(v) else to_hex(cmap(float(x))) for v, x in zip(values, t, strict=True)]

    def gradient(self, steps: int = 7) -> list[str]:
        cmap = colormaps[self.cmap]
        return [to_hex(cmap(i / (steps - 1))) for i in range(steps)]


RSRP = Scale("best-server SSB RSRP", "dBm", -130.0, -60.0, "viridis")
SINR = Scale("SS-SINR", "dB", -10.0, 30.0, "RdYlGn")
DIFF = Scale("difference", "dB", -10.0, 10.0, "RdBu_r")
COVERED, NOT_COVERED = "#1a9850", "#d73027"
CHANGED_CELL, CELL = "#e31a1c", "#1f4e9c"


def serving_colours(serving: np.ndarray, cell_ids: np.ndarray) -> list[str | None]:
    """A categorical colour per serving cell id (tab20, then tab20b: 40 distinct colours before one repeats);
    None where there is no server."""
    palette = [to_hex(c) for c in (*colormaps["tab20"].colors, *colormaps["tab20b"].colors)]  # type: ignore[attr-defined]
    index = {int(c): i for i, c in enumerate(np.sort(cell_ids))}
    return [None if s < 0 else palette[index.get(int(s), 0) % len(palette)] for s in np.asarray(serving)]
