"""A tiled model: one network answered by independent models of its tiles (issue 29).

A network too large for one model's budget is split into tiles of a few sites (:func:`rflscm.data.parts.plan_tiles`);
each tile is an ordinary model (RF-LSCM, WNOMP, …) fitted on its part of the scenario (its cells at their grids, the
other cells' SSB as interference).  :class:`TiledModel` holds the fitted tiles and answers a (cell, grid) pair with
the tile that owns the cell, so prediction, evaluation, maps and the optimiser read it as one network through the
:class:`~rflscm.models.source.APSSource` contract.

Its checkpoint is one ordinary checkpoint file (:meth:`LSCMModel.save`, :func:`load_model`): the state holds a
manifest (per tile: the model's name, its sites and cells), the cell → tile map, the full scenario's grid ids and
positions (so a grid is placed without ``grid_xyz``), and each tile's own checkpoint payload (model, fingerprint of
its part, run facts, angle grid, state): tensors, numbers and text only, read with ``weights_only``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import pandas as pd
import torch

from rflscm.errors import CheckpointError, UnsupportedError
from rflscm.geometry import AngleGrid
from rflscm.models.base import LSCMModel, model_from_payload, register_model

if TYPE_CHECKING:
    from rflscm.data.parts import Tile
    from rflscm.models.source import RsrpMix

MANIFEST_FORMAT = "rflscm-tiles/1"

__all__ = ["MANIFEST_FORMAT", "TiledModel"]


@register_model
class TiledModel(LSCMModel):
    """Per-tile models answering as one network; each (cell, grid) pair goes to its cell's tile."""

    name: ClassVar[str] = "tiled"

    def __init__(
        self,
        tiles: Sequence[LSCMModel],
        tile_sites: Sequence[Sequence[int]],
        tile_cells: Sequence[Sequence[int]],
        grid_ids: np.ndarray,
        grid_xyz: np.ndarray,
        device: torch.device | str = "cpu",
    ) -> None:
        if not tiles:
            raise CheckpointError("a tiled model needs at least one tile.")
        super().__init__(tiles[0].angle_grid, device)
        self.tiles = list(tiles)
        self.tile_sites = [tuple(int(s) for s in sites) for sites in tile_sites]
        self.tile_cells = [tuple(int(c) for c in cells) for cells in tile_cells]
        cells = np.concatenate([np.asarray(c, np.int64) for c in self.tile_cells])
        owner = np.concatenate([np.full(len(c), t, np.int64) for t, c in enumerate(self.tile_cells)])
        order = np.argsort(cells, kind="stable")
        self.cell_ids, self.cell_tile = cells[order], owner[order]
        grid_ids, grid_xyz = np.asarray(grid_ids, np.int64).reshape(-1), np.asarray(grid_xyz, np.float64).reshape(-1, 3)
        if len(grid_xyz) != len(grid_ids):
            raise CheckpointError(
                f"the tiled model holds {len(grid_ids)} grid ids and {len(grid_xyz)} positions (one per grid "
                "expected); the file is damaged: retrain it."
            )
        order = np.argsort(grid_ids, kind="stable")
        self.grid_ids, self.grid_xyz = grid_ids[order], grid_xyz[order]
        self.check_loaded()

    @classmethod
    def from_tiles(
        cls, tiles: Sequence[LSCMModel], plan: Sequence[Tile], grids: pd.DataFrame, device: torch.device | str = "cpu"
    ) -> TiledModel:
        """The tiled model of fitted ``tiles`` (one per tile of ``plan``, in order) over the full scenario's
        ``grids`` table (``grid_id``, ``x``, ``y``, ``z``)."""
        return cls(
            tiles,
            [t.sites for t in plan],
            [t.cells for t in plan],
            grids["grid_id"].to_numpy(np.int64),
            grids[["x", "y", "z"]].to_numpy(np.float64),
            device,
        )

    @property  # a tiled model sees unseen grids only when every tile does
    def supports_unseen_grids(self) -> bool:  # type: ignore[override]
        return all(t.supports_unseen_grids for t in self.tiles)

    @classmethod
    def build(
        cls, config: Any, angle_grid: AngleGrid, device: torch.device | str
    ) -> LSCMModel:  # pragma: no cover - see message
        raise UnsupportedError(
            "a tiled model is not built from a config: train one with `rflscm train --tile-sites K` "
            "(rflscm.train.tiles.fit_tiled)."
        )

    # --- answering ----------------------------------------------------------------------------
    def tile_of(self, cell_ids: np.ndarray) -> np.ndarray:
        """Tile index of each of ``cell_ids``; :class:`UnsupportedError` for a cell no tile owns."""
        cell_ids = np.asarray(cell_ids, dtype=np.int64).reshape(-1)
        pos = np.clip(np.searchsorted(self.cell_ids, cell_ids), 0, len(self.cell_ids) - 1)
        bad = self.cell_ids[pos] != cell_ids
        if bad.any():
            raise UnsupportedError(
                f"cell(s) {sorted(set(cell_ids[bad].tolist()))[:5]} belong to no tile of this tiled model (it was "
                "trained on another network); retrain it on this scenario."
            )
        return self.cell_tile[pos]

    def _positions(self, grid_ids: np.ndarray) -> np.ndarray | None:
        """Positions ``[n, 3]`` of ``grid_ids`` from the full scenario's grids; None when one is not known."""
        if len(self.grid_ids) == 0:
            return None
        pos = np.clip(np.searchsorted(self.grid_ids, grid_ids), 0, len(self.grid_ids) - 1)
        if (self.grid_ids[pos] != grid_ids).any():
            return None
        return self.grid_xyz[pos]

    def aps(self, cell_ids: np.ndarray, grid_ids: np.ndarray, grid_xyz: np.ndarray | None = None) -> torch.Tensor:
        """APS of each pair from the tile owning its cell (pairs grouped by tile, answers in the asked order).
        Without ``grid_xyz``, a tile that sees unseen grids is given the positions of the full scenario's grids
        (a grid outside the tile's own is placed there)."""
        cell_ids = np.asarray(cell_ids, dtype=np.int64).reshape(-1)
        grid_ids = np.asarray(grid_ids, dtype=np.int64).reshape(-1)
        xyz = None if grid_xyz is None else np.asarray(grid_xyz, np.float64).reshape(-1, 3)
        owner = self.tile_of(cell_ids)
        placed = self._positions(grid_ids) if xyz is None else xyz
        out = torch.zeros(len(cell_ids), self.angle_grid.num_bins, dtype=torch.float32, device=self.device)
        for t in np.unique(owner):
            rows = np.flatnonzero(owner == t)
            tile = self.tiles[int(t)]
            where = placed if tile.supports_unseen_grids else xyz
            answer = tile.aps(cell_ids[rows], grid_ids[rows], None if where is None else where[rows])
            out[torch.as_tensor(rows, device=self.device)] = answer.to(device=self.device, dtype=torch.float32)
        return out

    def level_offset_db(
        self, cell_ids: np.ndarray, beam_type: str, grid_ids: np.ndarray | None = None
    ) -> np.ndarray | None:
        """Each pair's offset from its cell's tile (0 where a tile has none); None when no tile has one."""
        cell_ids = np.asarray(cell_ids, dtype=np.int64).reshape(-1)
        grids = None if grid_ids is None else np.asarray(grid_ids, dtype=np.int64).reshape(-1)
        owner = self.tile_of(cell_ids)
        out, any_offset = np.zeros(len(cell_ids)), False
        for t in np.unique(owner):
            rows = np.flatnonzero(owner == t)
            offset = self.tiles[int(t)].level_offset_db(
                cell_ids[rows], beam_type, None if grids is None else grids[rows]
            )
            if offset is not None:
                out[rows], any_offset = np.asarray(offset, np.float64), True
        return out if any_offset else None

    def rsrp_mix(self, cell_ids: np.ndarray, grid_ids: np.ndarray, beam_type: str) -> RsrpMix | None:
        """Each pair's mix from its cell's tile (weight 0 where a tile has none); None when no tile has one."""
        from rflscm.models.source import RsrpMix, rsrp_mix_of

        cell_ids = np.asarray(cell_ids, dtype=np.int64).reshape(-1)
        grid_ids = np.asarray(grid_ids, dtype=np.int64).reshape(-1)
        owner = self.tile_of(cell_ids)
        aps = torch.zeros(len(cell_ids), self.angle_grid.num_bins, dtype=torch.float32, device=self.device)
        weight = torch.zeros(len(cell_ids), dtype=torch.float32, device=self.device)
        found = False
        for t in np.unique(owner):
            rows = np.flatnonzero(owner == t)
            mix = rsrp_mix_of(self.tiles[int(t)], cell_ids[rows], grid_ids[rows], beam_type)
            if mix is not None:
                at = torch.as_tensor(rows, device=self.device)
                aps[at] = mix.aps.to(self.device, torch.float32)
                weight[at] = mix.weight.to(self.device, torch.float32)
                found = True
        return RsrpMix(aps, weight) if found else None

    def round1_caps(self, cell_ids: np.ndarray, grid_ids: np.ndarray) -> np.ndarray | None:
        """Each pair's cap from its cell's tile (NaN where a tile has none); None when no tile has caps."""
        cell_ids = np.asarray(cell_ids, dtype=np.int64).reshape(-1)
        grid_ids = np.asarray(grid_ids, dtype=np.int64).reshape(-1)
        owner = self.tile_of(cell_ids)
        out, found = np.full(len(cell_ids), np.nan), False
        for t in np.unique(owner):
            rows = np.flatnonzero(owner == t)
            caps = getattr(self.tiles[int(t)], "round1_caps", None)
            got = None if caps is None else caps(cell_ids[rows], grid_ids[rows])
            if got is not None:
                out[rows], found = np.asarray(got, np.float64), True
        return out if found else None

    # --- persistence --------------------------------------------------------------------------
    def manifest(self) -> dict[str, Any]:
        """Plain facts of the tiling: format, and per tile its model, sites and cells."""
        return {
            "format": MANIFEST_FORMAT,
            "tiles": [
                {"model": tile.name, "sites": list(sites), "cells": list(cells)}
                for tile, sites, cells in zip(self.tiles, self.tile_sites, self.tile_cells, strict=True)
            ],
        }

    def state_dict_for_checkpoint(self) -> dict[str, Any]:
        return {
            "manifest": self.manifest(),
            "grid_ids": torch.as_tensor(self.grid_ids),
            "grid_xyz": torch.as_tensor(self.grid_xyz),
            "tiles": [
                {
                    "model": tile.name,
                    "fingerprint": tile.fingerprint,
                    "angle_grid": tile.angle_grid.to_dict(),
                    "run_info": tile.run_info,
                    "state": tile.state_dict_for_checkpoint(),
                }
                for tile in self.tiles
            ],
        }

    @classmethod
    def from_checkpoint(cls, state: dict[str, Any], device: torch.device | str = "cpu") -> TiledModel:
        from rflscm.models.base import MODEL_REGISTRY

        manifest, payloads = state.get("manifest"), state.get("tiles")
        if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
            raise CheckpointError(f"the tiled model's manifest is missing or not `{MANIFEST_FORMAT}`; retrain it.")
        entries = manifest.get("tiles")
        if not isinstance(entries, list) or not isinstance(payloads, list) or len(entries) != len(payloads):
            raise CheckpointError(
                f"the tiled model's manifest lists {len(entries) if isinstance(entries, list) else 'no'} tiles but the "
                f"file holds {len(payloads) if isinstance(payloads, list) else 'no'} tile checkpoints; retrain it."
            )
        tiles = []
        for i, (entry, payload) in enumerate(zip(entries, payloads, strict=True)):
            name = str(payload.get("model"))
            if name != entry.get("model") or name not in MODEL_REGISTRY or name == cls.name:
                raise CheckpointError(
                    f"tile {i} of the tiled model: the manifest names model {entry.get('model')!r}, its checkpoint "
                    f"holds {name!r} (a tile is one of {', '.join(sorted(set(MODEL_REGISTRY) - {cls.name}))}); "
                    "retrain it."
                )
            tiles.append(model_from_payload(payload, device))
        grid_ids, grid_xyz = state["grid_ids"].numpy(), state["grid_xyz"].numpy()
        return cls(tiles, [e["sites"] for e in entries], [e["cells"] for e in entries], grid_ids, grid_xyz, device)

    def check_loaded(self) -> None:
        """Every cell is owned by exactly one tile, every tile answers on the same angle grid, and the grid table
        is one position per distinct grid id."""
        cells = np.concatenate([np.asarray(c, np.int64) for c in self.tile_cells] or [np.empty(0, np.int64)])
        if len(self.tile_cells) != len(self.tiles) or len(self.tile_sites) != len(self.tiles):
            raise CheckpointError(
                f"the tiled model's manifest describes {len(self.tile_cells)} tiles for {len(self.tiles)} models; "
                "retrain it."
            )
        if len(np.unique(cells)) != len(cells):
            twice = pd.Series(cells).value_counts()
            raise CheckpointError(
                f"the tiled model's manifest gives cell {int(twice.index[0])} to {int(twice.iloc[0])} tiles (a cell "
                "belongs to exactly one); the file is damaged: retrain it."
            )
        for i, tile in enumerate(self.tiles):
            if tile.angle_grid != self.angle_grid:
                raise CheckpointError(f"tile {i} of the tiled model answers on another angle grid; retrain it.")
        if len(self.grid_xyz) != len(self.grid_ids) or len(np.unique(self.grid_ids)) != len(self.grid_ids):
            raise CheckpointError(
                f"the tiled model holds {len(self.grid_ids)} grid ids and {len(self.grid_xyz)} positions (one per "
                "distinct grid expected); the file is damaged: retrain it."
            )
