"""A tiled model answers each pair with its cell's tile, in the asked order (issue 29)."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from rflscm.errors import CheckpointError, UnsupportedError
from rflscm.geometry import AngleGrid
from rflscm.models.base import LSCMModel
from rflscm.models.source import RsrpMix
from rflscm.models.tiled import MANIFEST_FORMAT, TiledModel

GRID = AngleGrid(num_el=4, num_az=6, el_min_deg=-90.0, el_step_deg=60.0)


class Fake(LSCMModel):
    """A tile that answers a value made of its own tag, the cell, the grid and the position it was given."""

    name = "fake"

    def __init__(self, tag: float, unseen: bool = True, offset: float | None = None) -> None:
        super().__init__(GRID)
        self.tag, self.offset, self.calls = tag, offset, []
        self.unseen = unseen

    @property  # type: ignore[override]
    def supports_unseen_grids(self) -> bool:
        return self.unseen

    @classmethod
    def build(cls, config: Any, angle_grid: AngleGrid, device: Any) -> LSCMModel:
        raise NotImplementedError

    def aps(self, cell_ids: np.ndarray, grid_ids: np.ndarray, grid_xyz: np.ndarray | None = None) -> torch.Tensor:
        self.calls.append((cell_ids.copy(), grid_ids.copy(), None if grid_xyz is None else grid_xyz.copy()))
        out = torch.zeros(len(cell_ids), GRID.num_bins)
        out[:, 0] = self.tag
        out[:, 1] = torch.as_tensor(cell_ids, dtype=torch.float32)
        out[:, 2] = torch.as_tensor(grid_ids, dtype=torch.float32)
        if grid_xyz is not None:
            out[:, 3] = torch.as_tensor(grid_xyz[:, 0], dtype=torch.float32)
        return out

    def level_offset_db(
        self, cell_ids: np.ndarray, beam_type: str, grid_ids: np.ndarray | None = None
    ) -> np.ndarray | None:
        return None if self.offset is None else np.full(len(cell_ids), self.offset)

    def state_dict_for_checkpoint(self) -> dict[str, Any]:
        return {}

    @classmethod
    def from_checkpoint(cls, state: dict[str, Any], device: Any = "cpu") -> LSCMModel:
        raise NotImplementedError


def tiled(a: Fake, b: Fake) -> TiledModel:
    grid_ids = np.array([30, 10, 20])
    grid_xyz = np.array([[3.0, 0, 0], [1.0, 0, 0], [2.0, 0, 0]])
    return TiledModel([a, b], [(1,), (2,)], [(5, 7), (6,)], grid_ids, grid_xyz)


def test_each_pair_is_answered_by_its_cells_tile_in_the_asked_order() -> None:
    a, b = Fake(1.0), Fake(2.0)
    model = tiled(a, b)
    cells, grids = np.array([6, 5, 7, 6, 5]), np.array([10, 20, 30, 30, 10])
    xyz = np.arange(15.0).reshape(5, 3)
    out = model.aps(cells, grids, xyz)
    expected = torch.zeros(5, GRID.num_bins)
    rows_a, rows_b = np.array([1, 2, 4]), np.array([0, 3])
    expected[rows_a] = Fake(1.0).aps(cells[rows_a], grids[rows_a], xyz[rows_a])
    expected[rows_b] = Fake(2.0).aps(cells[rows_b], grids[rows_b], xyz[rows_b])
    assert torch.equal(out, expected)
    assert len(a.calls) == len(b.calls) == 1  # one call per tile: the pairs are grouped
    assert model.supports_unseen_grids and model.tile_of(np.array([7, 6])).tolist() == [0, 1]


def test_without_positions_a_field_tile_gets_the_full_grids_and_a_pair_table_tile_gets_none() -> None:
    a, b = Fake(1.0, unseen=True), Fake(2.0, unseen=False)
    model = tiled(a, b)
    out = model.aps(np.array([5, 6, 7]), np.array([20, 10, 30]))
    assert out[:, 3].tolist() == [2.0, 0.0, 3.0]  # tile a placed grids 20 and 30 from the model's grid table
    assert a.calls[0][2].tolist() == [[2.0, 0, 0], [3.0, 0, 0]] and b.calls[0][2] is None
    assert not model.supports_unseen_grids  # only when every tile does


def test_level_offsets_come_from_each_tile_and_none_when_no_tile_has_one() -> None:
    assert tiled(Fake(1.0), Fake(2.0)).level_offset_db(np.array([5, 6]), "csi") is None
    offsets = tiled(Fake(1.0, offset=3.0), Fake(2.0)).level_offset_db(np.array([6, 5, 7]), "csi")
    assert offsets.tolist() == [0.0, 3.0, 3.0]


class Mixing(Fake):
    """A tile that mixes a second APS (its own, doubled) into its even grids' predictions with weight 0.25."""

    def rsrp_mix(self, cell_ids: np.ndarray, grid_ids: np.ndarray, beam_type: str) -> RsrpMix | None:
        weight = torch.as_tensor(np.asarray(grid_ids) % 20 == 0, dtype=torch.float32) * (
            0.25 if beam_type == "ssb" else 0.5
        )
        return RsrpMix(2.0 * self.aps(cell_ids, grid_ids), weight)


def test_the_db_mix_comes_from_each_tile_and_none_when_no_tile_has_one() -> None:
    assert tiled(Fake(1.0), Fake(2.0)).rsrp_mix(np.array([5, 6]), np.array([10, 20]), "ssb") is None
    cells, grids = np.array([6, 5, 7, 5]), np.array([20, 20, 30, 10])
    mix = tiled(Mixing(1.0), Fake(2.0)).rsrp_mix(cells, grids, "ssb")
    assert mix is not None
    assert mix.weight.tolist() == [0.0, 0.25, 0.0, 0.0]  # cell 6 is tile b's (no mix); grid 20 of tile a mixes
    csi = tiled(Mixing(1.0), Fake(2.0)).rsrp_mix(cells, grids, "csi")
    assert csi is not None and csi.weight.tolist() == [0.0, 0.5, 0.0, 0.0]  # each beam type's own weight
    assert mix.aps[1, 0] == 2.0 and mix.aps[1, 1] == 10.0 and float(mix.aps[0].abs().sum()) == 0.0


def test_a_cell_no_tile_owns_is_unsupported() -> None:
    with pytest.raises(UnsupportedError, match=r"cell\(s\) \[8\] belong to no tile"):
        tiled(Fake(1.0), Fake(2.0)).aps(np.array([5, 8]), np.array([10, 10]))


def test_the_manifest_names_each_tile_and_a_cell_in_two_tiles_is_refused() -> None:
    model = tiled(Fake(1.0), Fake(2.0))
    assert model.manifest() == {
        "format": MANIFEST_FORMAT,
        "tiles": [{"model": "fake", "sites": [1], "cells": [5, 7]}, {"model": "fake", "sites": [2], "cells": [6]}],
    }
    with pytest.raises(CheckpointError, match="gives cell 7 to 2 tiles"):
        TiledModel([Fake(1.0), Fake(2.0)], [(1,), (2,)], [(5, 7), (7,)], np.array([1]), np.zeros((1, 3)))
    with pytest.raises(CheckpointError, match="2 grid ids and 1 positions"):
        TiledModel([Fake(1.0)], [(1,)], [(5,)], np.array([1, 2]), np.zeros((1, 3)))
