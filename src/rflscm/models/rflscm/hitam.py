"""HiTAM: hierarchical tensor angular modelling (paper §IV-B).

A coarse model renders one ray per β×β block of the angle grid (partial blocks at the edges);
the top-K_C blocks of each (cell, grid) are expanded into their fine bins Ω′, which a separate
refinement model renders.  L_total = (1 − α) L⁽¹⁾ + α L⁽²⁾, α rising from 0 to 1 after a coarse-only
warm-up.  The fine APS is the model's output: outside Ω′ it holds the coarse power of the blocks ranked next
(``hitam.outside: coarse``, the default) or zeros (``zero``, the paper's form).

Coarse columns (A⁽¹⁾): a coarse value x̃⁽¹⁾_J is read as the total power of block J spread over the
block, so its column is the *mean* of the block's fine columns and its ray goes through the block's
centre direction.  (The paper's literal form, the representative (first) bin's column and direction,
sits at the block's corner and aliases the beam pattern's slopes and nulls into the coarse fit; it
was removed in issue 11.)
"""

from __future__ import annotations

import torch

from rflscm.geometry import AngleGrid


class HiTAM:
    """Coarse/fine bin bookkeeping for one :class:`AngleGrid` (no parameters)."""

    def __init__(self, grid: AngleGrid, beta: int, top_k: int, warmup_steps: int = 1000, ramp_steps: int = 500) -> None:
        self.grid, self.beta = grid, beta
        self.mapping = grid.coarse(beta)
        self.top_k = min(top_k, self.mapping.num_bins)
        self.warmup_steps, self.ramp_steps = warmup_steps, ramp_steps
        self.children, self.valid = self.mapping.children(torch.arange(self.mapping.num_bins))  # [Nc, β²]

    @property
    def num_coarse(self) -> int:
        return self.mapping.num_bins

    @property
    def num_fine_slots(self) -> int:
        """|Ω′| slots per pair, β² K_C (some invalid in partial edge blocks)."""
        return self.top_k * self.beta**2

    def coarse_directions(self) -> torch.Tensor:
        """Unit vectors ``[num_coarse, 3]`` of the coarse rays."""
        fine = self.grid.directions(dtype=torch.float64)
        weights = self.valid.to(torch.float64)  # [Nc, β²]
        centre = (fine[self.children] * weights[..., None]).sum(1)
        return (centre / centre.norm(dim=-1, keepdim=True)).float()

    def coarse_columns(self, a_full: torch.Tensor) -> torch.Tensor:
        """A⁽¹⁾ ``[..., num_beams, num_coarse]`` from the full ``A [..., num_beams, num_bins]``."""
        children = self.children.to(a_full.device)
        weights = self.valid.to(a_full.device, a_full.dtype)
        block = a_full[..., children] * weights  # [..., M, Nc, β²]
        return block.sum(-1) / weights.sum(-1)

    def ranked(self, coarse_power: torch.Tensor, count: int | None = None) -> torch.Tensor:
        """The ``count`` (default K_C) coarse bins ``[B, count]`` of largest ``coarse_power [B, num_coarse]``, largest
        first."""
        k = min(self.top_k if count is None else count, coarse_power.shape[-1])
        return torch.topk(coarse_power, k, dim=-1).indices

    def expand(self, coarse_power: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Top-K_C coarse bins of ``coarse_power [B, num_coarse]`` (:meth:`ranked`) → fine bins and validity
        ``[B, β² K_C]``."""
        return self.refined(self.ranked(coarse_power))

    def refined(self, blocks: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Fine bins and validity ``[B, β² J]`` of coarse ``blocks [B, J]``."""
        fine, valid = self.mapping.children(blocks)  # [B, J, β²]
        return fine.flatten(1), valid.flatten(1)

    def spread(
        self, coarse_power: torch.Tensor, blocks: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Coarse ``blocks [B, J]`` as fine bins: ``(fine bins, values, valid) [B, β² J]``, each block's power of
        ``coarse_power [B, num_coarse]`` spread evenly over its bins (the coarse value is a block's total power)."""
        fine, valid = self.mapping.children(blocks)  # [B, J, β²]
        share = valid / valid.sum(-1, keepdim=True).clamp_min(1)
        values = coarse_power.gather(1, blocks)[..., None] * share
        return fine.flatten(1), values.flatten(1), valid.flatten(1)

    def alpha(self, position: float) -> float:
        """α at schedule ``position`` (a step, 0-based, or a fractional position of a time-budget run): 0 during
        the warm-up, then a linear ramp to 1."""
        if position < self.warmup_steps:
            return 0.0
        if self.ramp_steps == 0:
            return 1.0
        return min(1.0, (position - self.warmup_steps + 1) / self.ramp_steps)


def scatter_fine(values: torch.Tensor, fine_bins: torch.Tensor, valid: torch.Tensor, num_bins: int) -> torch.Tensor:
    """Dense fine APS ``[B, num_bins]`` from values at ``fine_bins [B, K′]`` (zeros elsewhere and at invalid slots)."""
    out = values.new_zeros(values.shape[0], num_bins)
    return out.scatter_add(1, fine_bins, values * valid.to(values.dtype))
