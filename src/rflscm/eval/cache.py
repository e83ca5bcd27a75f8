"""The one APS cache: a fitted model whose APS of each (cell, grid) pair is computed once.

Evaluation asks for the APS of a pair once per beam type (through ``predict_rsrp``) and again for the
APS metrics; the benchmarks ask again (false reports, APS recovery) and ``rflscm predict`` once per beam
type.  A field model renders the APS each time, so :func:`rflscm.eval.run_evaluation`, the benchmark
harness and the CLI all wrap the model in :class:`APSCache`; the models themselves keep no APS.
Rows are stored sparse (the nonzero bins: HiTAM's K_C β² refined bins, WNOMP's atoms), so a cache of
every test pair fits in memory even at full size.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from rflscm.errors import UnsupportedError
from rflscm.geometry import AngleGrid
from rflscm.models.base import LSCMModel


class APSCache(LSCMModel):
    """A view of the fitted model ``inner`` that remembers its APS per ``(cell_id, grid_id)``.

    Everything but :meth:`aps` is the wrapped model's (name, fingerprint, run information); it
    neither learns nor saves.  Only use it while ``inner``'s weights do not change.
    """

    def __init__(self, inner: LSCMModel) -> None:
        super().__init__(inner.angle_grid, inner.device)
        self.inner = inner
        self.name = inner.name  # type: ignore[misc]
        self.supports_unseen_grids = inner.supports_unseen_grids  # type: ignore[misc]
        self.fingerprint, self.run_info = inner.fingerprint, inner.run_info
        self._rows: dict[tuple[int, int], tuple[torch.Tensor, torch.Tensor]] = {}

    @staticmethod
    def of(model: LSCMModel) -> APSCache:
        """``model`` itself when it is a cache already, else a fresh cache of it."""
        return model if isinstance(model, APSCache) else APSCache(model)

    def __len__(self) -> int:
        return len(self._rows)

    def aps(self, cell_ids: np.ndarray, grid_ids: np.ndarray, grid_xyz: np.ndarray | None = None) -> torch.Tensor:
        cell_ids, grid_ids = np.asarray(cell_ids).reshape(-1), np.asarray(grid_ids).reshape(-1)
        keys = list(zip(cell_ids.tolist(), grid_ids.tolist(), strict=True))
        todo = np.array(
            sorted({i for i, k in enumerate(keys) if k not in self._rows} - _later_duplicates(keys)), np.int64
        )
        if todo.size:
            xyz = None if grid_xyz is None else np.asarray(grid_xyz).reshape(-1, 3)[todo]
            rows = self.inner.aps(cell_ids[todo], grid_ids[todo], xyz).detach()
            for i, row in zip(todo.tolist(), rows, strict=True):
                bins = torch.nonzero(row).squeeze(1)
                self._rows[keys[i]] = (bins, row[bins].clone())
        out = torch.zeros(len(keys), self.angle_grid.num_bins, device=self.device)
        for j, key in enumerate(keys):
            bins, values = self._rows[key]
            out[j, bins.to(self.device)] = values.to(self.device)
        return out

    def level_offset_db(self, cell_ids: np.ndarray, beam_type: str) -> np.ndarray | None:
        return self.inner.level_offset_db(cell_ids, beam_type)

    # the contract's learning and persistence belong to the wrapped model
    @classmethod
    def build(
        cls, config: str | Path | dict[str, Any] | None, angle_grid: AngleGrid, device: torch.device | str
    ) -> LSCMModel:
        raise UnsupportedError("an APS cache wraps a fitted model")

    def state_dict_for_checkpoint(self) -> dict[str, Any]:
        raise UnsupportedError("an APS cache wraps a fitted model; save the model itself")

    @classmethod
    def from_checkpoint(cls, state: dict[str, Any], device: torch.device | str = "cpu") -> LSCMModel:
        raise UnsupportedError("an APS cache wraps a fitted model")


def _later_duplicates(keys: list[tuple[int, int]]) -> set[int]:
    """Positions of keys that occur earlier in ``keys`` (computed once, by their first position)."""
    seen: set[tuple[int, int]] = set()
    later = set()
    for i, key in enumerate(keys):
        if key in seen:
            later.add(i)
        seen.add(key)
    return later
