"""Which cell a sample belongs to: by ``cell_id``, or by (PCI, carrier) → the nearest such cell.

A sample with a PCI on a carrier is given to the nearest cell (2D distance, the cell list of the sample's
round) that has that PCI on that carrier (carriers match to 100 kHz), provided it lies within
``max_distance_m``.  When a second such cell lies within the limit and less than ``ambiguity_ratio`` times
as far as the nearest, the sample is *ambiguous* (PCI reuse too close to tell).  Samples with no such cell,
too far or ambiguous are dropped and counted per reason; so are ``cell_id`` values the list does not have
and samples farther than ``max_distance_m`` from the cell they name (a bad GPS fix).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from rflscm.data.ingest.samples import Tally
from rflscm.data.ingest.spec import ImportSpec

CARRIER_MATCH_HZ = 1e5
"""Carriers within this of each other (after ARFCN conversion) are the same carrier."""

NO_CELL = "(PCI, carrier) matches no cell of the list"
TOO_FAR = "(PCI, carrier): nearest such cell beyond max_distance_m"
AMBIGUOUS = "(PCI, carrier): ambiguous (two such cells at similar distance)"
UNKNOWN_ID = "cell_id not in the cell list"
FAR_FROM_ID = "cell_id: farther than max_distance_m from that cell (a bad GPS fix?)"


def resolve_cells(
    samples: pd.DataFrame, cells: dict[int, pd.DataFrame], ids: dict[str, int], spec: ImportSpec, tally: Tally
) -> pd.DataFrame:
    """``samples`` (from :func:`read_samples`) with ``cell_id`` filled; unresolvable rows removed and counted.

    Args:
        cells: per round the cells table of :func:`cells_frame` (``cell_id, x, y, pci, carrier_hz``).
        ids: cell name → cell id.
    """
    by_name = samples["pci"].to_numpy() < 0
    cell_id = np.full(len(samples), -1, dtype=np.int64)
    names = samples["cell_name"].to_numpy()[by_name]
    cell_id[by_name] = pd.Series(names, dtype=object).map(ids).fillna(-1).to_numpy(np.int64)
    tally.drop(UNKNOWN_ID, int((cell_id[by_name] < 0).sum()))
    if by_name.any():
        cell_id[by_name] = _near_enough(samples[by_name], cell_id[by_name], cells, spec, tally)
    if (~by_name).any():
        cell_id[~by_name] = _by_pci(samples[~by_name], cells, spec, tally)
    out = samples.assign(cell_id=cell_id)
    return out[cell_id >= 0].reset_index(drop=True)


def _near_enough(
    samples: pd.DataFrame, cell_id: np.ndarray, cells: dict[int, pd.DataFrame], spec: ImportSpec, tally: Tally
) -> np.ndarray:
    """``cell_id`` with −1 where the sample lies farther than ``max_distance_m`` from its (named) cell."""
    table = pd.concat([c[["cell_id", "x", "y"]].assign(round=r) for r, c in cells.items()], ignore_index=True)
    at = pd.MultiIndex.from_arrays([samples["round"].to_numpy(), cell_id])
    pos = table.set_index(["round", "cell_id"]).reindex(at)
    d = np.hypot(samples["x"].to_numpy() - pos["x"].to_numpy(), samples["y"].to_numpy() - pos["y"].to_numpy())
    far = (cell_id >= 0) & (d > spec.max_distance_m)  # NaN (unknown cell) compares False
    tally.drop(FAR_FROM_ID, int(far.sum()))
    return np.where(far, -1, cell_id)


def _by_pci(samples: pd.DataFrame, cells: dict[int, pd.DataFrame], spec: ImportSpec, tally: Tally) -> np.ndarray:
    table = pd.concat([c.assign(round=r) for r, c in cells.items()], ignore_index=True)
    key = ["round", "pci", "band"]
    table = table.assign(band=np.round(table["carrier_hz"] / CARRIER_MATCH_HZ).astype(np.int64))
    left = samples[["round", "pci", "x", "y"]].assign(
        sid=np.arange(len(samples)), band=np.round(samples["carrier_hz"] / CARRIER_MATCH_HZ).astype(np.int64)
    )
    pairs = left.merge(table[[*key, "cell_id", "x", "y"]], on=key, suffixes=("", "_cell"))
    pairs["d"] = np.hypot(pairs["x"] - pairs["x_cell"], pairs["y"] - pairs["y_cell"])
    pairs = pairs.sort_values(["sid", "d"], kind="stable")
    rank = pairs.groupby("sid").cumcount().to_numpy()
    first = pairs[rank == 0].set_index("sid")
    second = pairs[rank == 1].set_index("sid")["d"].reindex(first.index)
    out = np.full(len(samples), -1, dtype=np.int64)
    d1 = first["d"].to_numpy()
    d2 = second.to_numpy()
    far = d1 > spec.max_distance_m
    ambiguous = ~far & (d2 <= spec.max_distance_m) & (d2 < spec.ambiguity_ratio * d1)
    good = ~far & ~ambiguous
    out[first.index.to_numpy()[good]] = first["cell_id"].to_numpy()[good]
    tally.drop(NO_CELL, len(samples) - len(first))
    tally.drop(TOO_FAR, int(far.sum()))
    tally.drop(AMBIGUOUS, int(ambiguous.sum()))
    return out
