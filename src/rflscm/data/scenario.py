"""The in-memory scenario: cells per round, grids, measurements, point cloud, and the views models use.

A :class:`Scenario` is built by :func:`rflscm.data.load_scenario`, which has
validated and normalised every table; the accessors below can therefore assume
clean data.  Antenna objects and sensing matrices come straight from
:mod:`rflscm.antenna`, so a model never re-implements the cell table's meaning.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import torch

from rflscm.antenna import (
    ArrayGeometry,
    CellAntenna,
    Codebook,
    ElementPattern,
    TR38901Element,
    read_msi,
    sensing_matrix,
    wavelength_of,
)
from rflscm.data.cells import CELL_COLUMNS, DEFAULT_ELEMENT
from rflscm.data.columns import TableRef, fmt_list
from rflscm.data.measurements import (
    BEAM_TYPES,
    MEASUREMENT_COLUMNS,
    codebook_sizes,
    normalise_measurements,
)
from rflscm.data.meta import ScenarioMeta
from rflscm.data.pointcloud import PointCloud
from rflscm.data.positions import GRID_COLUMNS
from rflscm.errors import ConfigError, DataError
from rflscm.geometry import AngleGrid

OUTSIDE_SSB_COLUMNS = ("round", "grid_id", "freq_hz", "beam_id", "rsrp_dbm")
"""Columns of :attr:`Scenario.outside_ssb`."""


@dataclass(eq=False)
class Scenario:
    """A validated scenario.

    Attributes:
        root: the scenario folder (absolute).
        meta: scenario.yaml.
        cells: round → cells table (see :mod:`rflscm.data.cells`): x/y/z always present, defaults
            filled, sorted by ``cell_id`` with a 0…n−1 index; every round has the same cell ids.
        grids: ``grid_id``, ``x``, ``y``, ``z`` [m] (+ extra columns), sorted by ``grid_id``.
        measurements: long-form RSRP (see :mod:`rflscm.data.measurements`), in file order.
        point_cloud: the building/ground scan, or ``None``.
        outside_ssb: for a part cut from a larger scenario (the benchmarks' subsets), the reported SSB of the
            cells left out at the kept grids (``round``, ``grid_id``, ``freq_hz``, ``beam_id``, ``rsrp_dbm``):
            interference that the SS-SINR detection level of :mod:`rflscm.data.reporting` must still count.
            ``None`` for a scenario loaded from its folder.

    ``==`` compares contents (meta without file names, tables, point cloud, ``outside_ssb``), not locations.
    """

    root: Path
    meta: ScenarioMeta
    cells: dict[int, pd.DataFrame]
    grids: pd.DataFrame
    measurements: pd.DataFrame
    point_cloud: PointCloud | None = None
    outside_ssb: pd.DataFrame | None = None
    _elements: dict[str, ElementPattern] = field(default_factory=dict, init=False, repr=False)

    # ---- ids and per-cell facts --------------------------------------------------------------
    def cell_ids(self) -> np.ndarray:
        """Sorted cell ids ``[num_cells]`` (int64), the same in every round."""
        return self.cells[1]["cell_id"].to_numpy().copy()

    def grid_ids(self) -> np.ndarray:
        """Sorted grid ids ``[num_grids]`` (int64)."""
        return self.grids["grid_id"].to_numpy().copy()

    def rounds(self) -> list[int]:
        """Measurement rounds with a cells table, ascending (round 1 first)."""
        return sorted(self.cells)

    def _check_round(self, round: int) -> int:
        if round not in self.cells:
            raise DataError(f"round {round} has no cells table; rounds: {fmt_list(self.rounds())}.")
        return round

    def cell_row(self, cell_id: int, round: int = 1) -> pd.Series:
        """The normalised cells-table row of ``cell_id`` in ``round``."""
        table = self.cells[self._check_round(round)]
        ids = table["cell_id"].to_numpy()
        pos = int(np.searchsorted(ids, cell_id))
        if pos >= len(ids) or ids[pos] != cell_id:
            raise DataError(f"cell_id {cell_id} is not a cell of this scenario (cell ids: {fmt_list(ids)}).")
        return table.iloc[pos]

    def cell_position(self, cell_id: int) -> np.ndarray:
        """Antenna position ``[3]`` (x, y, z) [m] in the ENU frame."""
        return self.cell_row(cell_id)[["x", "y", "z"]].to_numpy(dtype=np.float64)

    def freq_hz(self, cell_id: int) -> float:
        """Carrier frequency [Hz] of the cell."""
        return float(self.cell_row(cell_id)["freq_hz"])

    def wavelength_m(self, cell_id: int) -> float:
        """Carrier wavelength [m] of the cell."""
        return wavelength_of(self.freq_hz(cell_id))

    # ---- antenna, codebooks, sensing matrix ---------------------------------------------------
    def element(self, name: str) -> ElementPattern:
        """Element pattern of an ``element`` value (``tr38901`` or an MSI file relative to :attr:`root`)."""
        if name not in self._elements:
            self._elements[name] = TR38901Element() if name == DEFAULT_ELEMENT else read_msi(self.root / name)
        return self._elements[name]

    def antenna(self, cell_id: int, round: int = 1) -> CellAntenna:
        """The cell's antenna (orientation, array, element, RS power) in ``round``."""
        row = self.cell_row(cell_id, round)
        array = ArrayGeometry(
            num_h=int(row["array_nh"]),
            num_v=int(row["array_nv"]),
            spacing_h_m=float(row["spacing_h_m"]),
            spacing_v_m=float(row["spacing_v_m"]),
        )
        return CellAntenna(
            azimuth_deg=float(row["azimuth_deg"]),
            mech_tilt_deg=float(row["mech_tilt_deg"]),
            elec_tilt_deg=float(row["elec_tilt_deg"]),
            array=array,
            element=self.element(str(row["element"])),
            tx_power_dbm=float(row["tx_power_dbm"]),
        )

    def codebook(self, cell_id: int, beam_type: str, round: int = 1) -> Codebook:
        """The cell's ``ssb`` or ``csi`` codebook in ``round``."""
        return self.meta.codebooks[str(self.cell_row(cell_id, round)[f"{_beam_type(beam_type)}_codebook"])]

    def num_beams(self, cell_id: int, beam_type: str, round: int = 1) -> int:
        """Number of beams of the cell's ``ssb`` or ``csi`` codebook in ``round``."""
        return int(self.codebook(cell_id, beam_type, round).num_beams)

    def sensing(
        self,
        cell_id: int,
        beam_type: str,
        directions: AngleGrid | torch.Tensor,
        round: int = 1,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """Sensing matrix ``[num_beams, num_dirs]`` [mW per unit path gain] of the cell's beams.

        ``directions``: an :class:`AngleGrid` or world-frame unit vectors ``[num_dirs, 3]``;
        see :func:`rflscm.antenna.sensing_matrix`.
        """
        return sensing_matrix(
            self.antenna(cell_id, round),
            self.codebook(cell_id, beam_type, round),
            directions,
            self.wavelength_m(cell_id),
            dtype=dtype,
            device=device,
        )

    # ---- measurements --------------------------------------------------------------------------
    def rsrp_table(self, round: int, beam_type: str) -> tuple[pd.DataFrame, np.ndarray]:
        """Wide RSRP of one round and beam type.

        Returns:
            ``(pairs, rsrp_dbm)``: ``pairs`` has ``cell_id``, ``grid_id`` of every (cell, grid) with at
            least one row, sorted by (cell_id, grid_id); ``rsrp_dbm`` is float64
            ``[num_pairs, max_beams]`` [dBm], NaN where missing, ``max_beams`` being the largest
            codebook of that type among the round's cells (beams beyond a cell's codebook are NaN).
        """
        t = BEAM_TYPES.index(_beam_type(beam_type))
        round_pos = self.rounds().index(self._check_round(round))
        sizes = codebook_sizes(self.cells, self.meta)[round_pos, :, t]  # [num_cells]
        m = self.measurements
        sel = ((m["round"] == round) & (m["beam_type"] == BEAM_TYPES[t])).to_numpy()
        cell_ids, grid_ids = self.cell_ids(), self.grid_ids()
        c = np.searchsorted(cell_ids, m["cell_id"].to_numpy()[sel])
        g = np.searchsorted(grid_ids, m["grid_id"].to_numpy()[sel])
        pair_keys, pair_of_row = np.unique(c * len(grid_ids) + g, return_inverse=True)
        rsrp = np.full((len(pair_keys), int(sizes.max())), np.nan)
        rsrp[pair_of_row, m["beam_id"].to_numpy()[sel]] = m["rsrp_dbm"].to_numpy()[sel]
        pairs = pd.DataFrame(
            {"cell_id": cell_ids[pair_keys // len(grid_ids)], "grid_id": grid_ids[pair_keys % len(grid_ids)]}
        )
        return pairs, rsrp

    def with_measurements(self, measurements: pd.DataFrame, validate: bool = True) -> Scenario:
        """A copy sharing everything but the measurements (e.g. a hold-out split).

        The table is validated like a file (rows numbered in its order) unless ``validate`` is False
        (only for tables taken from this scenario's own, already valid, measurements).
        """
        if validate:
            grids_name = self.meta.grids
            ref = TableRef("measurements (replacement table)")
            measurements = normalise_measurements(measurements, ref, self.meta, self.cells, self.grid_ids(), grids_name)
        else:
            measurements = measurements.reset_index(drop=True)
        new = dataclasses.replace(self, measurements=measurements)
        new._elements.update(self._elements)
        return new

    # ---- identity --------------------------------------------------------------------------------
    def fingerprint(self) -> str:
        """SHA-256 (hex) of round-1 cells, grids, round-1 measurements (and round-1 ``outside_ssb``, where a
        cut-out part has it) and the data-relevant meta.

        The meta part is threshold, carriers and codebooks (names, descriptions, file names and the
        geographic origin, which only places the frame on Earth, are not data).  Only the standard columns are hashed, in canonical dtypes, so the value
        is the same after save/load and for CSV and Parquet files.
        """
        digest = hashlib.sha256()
        meta = self.meta.to_dict()
        meta_part = {k: meta[k] for k in ("rsrp_threshold_dbm", "frequencies_hz", "codebooks")}
        # The origin only places the frame on Earth; the tables are hashed in the frame (lat/lon inputs projected
        # already), so a georeference added later (maps) keeps checkpoints valid.  Hashed as null, as before.
        meta_part["origin"] = None
        if "reporting" in meta:
            meta_part["reporting"] = meta["reporting"]
        digest.update(json.dumps(meta_part, sort_keys=True).encode())
        m = self.measurements
        _hash_table(digest, "cells", self.cells[1], CELL_COLUMNS)
        _hash_table(digest, "grids", self.grids, GRID_COLUMNS)
        _hash_table(digest, "measurements", m, MEASUREMENT_COLUMNS, rows=(m["round"] == 1).to_numpy())
        if self.outside_ssb is not None:  # a cut-out part: the left-out cells' SSB sets its detection bounds
            outside = self.outside_ssb
            _hash_table(digest, "outside_ssb", outside[(outside["round"] == 1).to_numpy()], OUTSIDE_SSB_COLUMNS)
        return digest.hexdigest()

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Scenario):
            return NotImplemented
        return (
            self.meta.content() == other.meta.content()
            and sorted(self.cells) == sorted(other.cells)
            and all(self.cells[r].equals(other.cells[r]) for r in self.cells)
            and self.grids.equals(other.grids)
            and self.measurements.equals(other.measurements)
            and self.point_cloud == other.point_cloud
            and _same_table(self.outside_ssb, other.outside_ssb)
        )

    __hash__ = None  # type: ignore[assignment]  # mutable tables


def _beam_type(beam_type: str) -> str:
    text = str(beam_type).strip().lower()
    if text not in BEAM_TYPES:
        raise ConfigError(f"beam type must be one of {', '.join(BEAM_TYPES)} (got {beam_type!r}).")
    return text


def _same_table(a: pd.DataFrame | None, b: pd.DataFrame | None) -> bool:
    return (a is None and b is None) or (a is not None and b is not None and a.equals(b))


def _hash_table(
    digest: hashlib._Hash, label: str, table: pd.DataFrame, columns: tuple[str, ...], rows: np.ndarray | None = None
) -> None:
    """Feed a table's standard columns (of the ``rows`` where True; all rows by default) into ``digest`` in a
    dtype-canonical byte form, one column at a time (the selected rows are never copied as a table)."""
    digest.update(f"{label}:{len(table) if rows is None else int(rows.sum())}".encode())
    for column in columns:
        digest.update(f"|{column}|".encode())
        dtype = table[column].dtype
        if isinstance(dtype, pd.StringDtype) or pd.api.types.is_object_dtype(
            dtype
        ):  # text: never one Python object per row
            _hash_text(digest, table[column] if rows is None else table[column][rows])
            continue
        values = table[column].to_numpy() if rows is None else table[column].to_numpy()[rows]
        if values.dtype.kind in "iub":
            digest.update(np.ascontiguousarray(values, dtype=np.int64).tobytes())
        elif values.dtype.kind == "f":
            values = np.where(np.isnan(values), np.nan, values).astype(np.float64)  # one NaN bit pattern
            digest.update(np.ascontiguousarray(values).tobytes())
        else:
            _hash_text(digest, table[column] if rows is None else table[column][rows])


def _hash_text(digest: hashlib._Hash, series: pd.Series) -> None:
    """Feed the values of a text column joined by ``\\x1f`` (empty for missing) into ``digest``, in blocks of rows
    (the bytes of one join of them all)."""
    for start in range(0, len(series), _TEXT_BLOCK):
        if start:
            digest.update(b"\x1f")
        block = series.iloc[start : start + _TEXT_BLOCK]
        digest.update("\x1f".join(block.fillna("").astype(str).tolist()).encode())


_TEXT_BLOCK = 1 << 20
"""Rows of a text column joined at once when hashing."""


class SensingCache:
    """A view of ``scenario`` that keeps its sensing matrices on an :class:`AngleGrid` (every other attribute is the
    scenario's), so that several models predicting the same cells share them: the model and the oracle one cell after
    the other (``size`` 4), or the candidates of WNOMP's selection (``size`` None: every cell's, about 1 MB a cell on
    the default grid)."""

    def __init__(self, scenario: Scenario, size: int | None = 4) -> None:
        self._scenario = scenario
        self._size = size
        self._cache: dict[tuple, torch.Tensor] = {}

    def __getattr__(self, name: str) -> object:
        return getattr(self._scenario, name)

    def sensing(
        self,
        cell_id: int,
        beam_type: str,
        directions: AngleGrid | torch.Tensor,
        round: int = 1,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str | None = None,
    ) -> torch.Tensor:
        """:meth:`Scenario.sensing`, computed once per cell, beam type, grid, round, dtype and device."""
        if not isinstance(directions, AngleGrid):
            return self._scenario.sensing(cell_id, beam_type, directions, round=round, dtype=dtype, device=device)
        key = (int(cell_id), beam_type, directions, round, dtype, str(device))
        if key not in self._cache:
            if self._size is not None and len(self._cache) >= self._size:
                self._cache.pop(next(iter(self._cache)))
            self._cache[key] = self._scenario.sensing(
                cell_id, beam_type, directions, round=round, dtype=dtype, device=device
            )
        return self._cache[key]
