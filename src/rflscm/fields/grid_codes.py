"""Learned per-grid codes: a latent vector for every measured grid, interpolated between grids.

An auto-decoder embedding in the spirit of DeepSDF's shape codes and NeRF-W's appearance codes:
each grid with round-1 measurements owns a free code ``z_l [D]``, trained with the fields, that
the radiance decoder reads beside PE(p_l).  The tensor fields must explain every grid with a few
rank-1 components; the code gives each grid the freedom a per-grid model (WNOMP) has, while the
fields and the decoder stay shared.

Any position is answered: the code of a grid the table holds is its own (its weight is ~1e8 times
any other's), and a position between grids (an unseen grid) gets the inverse-squared-distance
mean of its ``k`` nearest table codes.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

EXACT_M = 1e-3
"""Distances are softened by this much [m], so a query on a table grid takes that grid's code."""


class GridCodes(nn.Module):
    """``[Q, 3] → [Q, dim]``: codes of table grids at ``positions [G, 3]``, interpolated elsewhere."""

    positions: torch.Tensor

    def __init__(self, positions: torch.Tensor, dim: int, neighbours: int = 4, chunk: int = 4096) -> None:
        super().__init__()
        if positions.ndim != 2 or positions.shape[1] != 3 or positions.shape[0] == 0:
            raise ValueError(f"GridCodes needs positions [G>0, 3] (got {tuple(positions.shape)}).")
        self.register_buffer("positions", positions.detach().float().clone())
        self.codes = nn.Parameter(torch.zeros(positions.shape[0], dim))
        self.neighbours, self.chunk = neighbours, chunk

    def weights(self, xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(index [Q, k], weight [Q, k])``: the ``k`` nearest table grids of each query and their
        normalised inverse-squared-distance weights (no gradient: positions are data)."""
        k = min(self.neighbours, self.positions.shape[0])
        index, weight = [], []
        with torch.no_grad():
            for start in range(0, xyz.shape[0], self.chunk):  # [chunk, G] distances at a time
                d2 = torch.cdist(xyz[start : start + self.chunk].float(), self.positions).square()
                near, idx = torch.topk(d2, k, dim=1, largest=False)
                w = 1.0 / (near + EXACT_M**2)
                index.append(idx)
                weight.append(w / w.sum(1, keepdim=True))
        if not index:
            return xyz.new_zeros((0, k), dtype=torch.long), xyz.new_zeros((0, k))
        return torch.cat(index), torch.cat(weight)

    def forward(self, xyz: torch.Tensor) -> torch.Tensor:
        index, weight = self.weights(xyz)
        return (self.codes[index] * weight[..., None]).sum(1)

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any, **kwargs: Any) -> None:
        # the table's size comes from the checkpoint (the model is built before its weights are read)
        codes, positions = state_dict.get(prefix + "codes"), state_dict.get(prefix + "positions")
        if codes is not None and positions is not None and codes.shape != self.codes.shape and codes.shape[0] == positions.shape[0]:
            self.positions = torch.empty_like(positions, device=self.positions.device)
            self.codes = nn.Parameter(torch.empty(codes.shape, device=self.codes.device))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
