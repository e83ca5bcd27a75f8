"""The APS renderer of radiance-field LSCM models: rays, visibility, HiTAM's selection, the sparse APS.

:class:`APSRenderer` is composed into :class:`~rflscm.models.rflscm.RFLSCM` (and so NeRF²-LSCM);
it owns no parameters (the stages do) and keeps its ray geometry in a typed :class:`RayCache`.
Rays are identified by (cell, direction): ``kind="coarse"`` uses HiTAM's coarse directions,
``kind="fine"`` the angle grid's bins.  Their stored samples (Φ > 0 plus FDAM neighbours) are
computed once per cell and kept (:func:`rflscm.render.build_ray_samples`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import nn

from rflscm.geometry import AngleGrid
from rflscm.models.pairs import PairData
from rflscm.models.rflscm.config import RFLSCMConfig
from rflscm.models.rflscm.fields import Queries, RayBatch
from rflscm.models.rflscm.hitam import HiTAM
from rflscm.models.rflscm.scene import SceneInfo
from rflscm.render import RaySamples, build_ray_samples, chunk_bounds, chunked, gather_samples

RayKind = Literal["coarse", "fine"]

FILL_BLOCKS = 3
"""With ``hitam.outside: coarse``, the coarse blocks per refined block (× K_C) ranked after Ω′ whose coarse power fills
the APS (every other block stays zero): on a 10-minute field checkpoint 3 × 16 blocks gave what all of them did."""


@dataclass
class RaySet:
    """The rays of one kind, for every cell: directions, cone radii, stored samples and visibility."""

    directions: torch.Tensor
    """``[num_dirs, 3]`` unit vectors."""
    radii: torch.Tensor
    """``[num_dirs]`` angular radius of each direction's bin (its cone) [rad]."""
    samples: RaySamples | None = None
    """Stored samples of every (cell, direction) ray, ray id ``cell * num_dirs + direction`` (built on demand)."""
    live: torch.Tensor | None = None
    """``[num_rays]`` live samples per ray (the cost of decoding it)."""
    visible: torch.Tensor | None = None
    """``[num_cells, num_dirs]`` bool: directions the cell's round-1 beams see (``render.min_gain_db``)."""


@dataclass
class RayCache:
    """What the renderer computes once per fitted scene (and drops when the scene or the weights change)."""

    cells: tuple[torch.Tensor, torch.Tensor] | None = None
    """Cell positions ``[C, 3]`` and wavelengths ``[C]`` on the device (float32)."""
    rays: dict[RayKind, RaySet] = field(default_factory=dict)


class APSRenderer:
    """Renders x̃ (normalised) of (cell, grid) pairs with a model's stages; HiTAM's selection on top.

    Args:
        config: the model's config (render, prior and HiTAM sections are read).
        angle_grid: the fine directions.
        hitam: HiTAM's coarse directions and selection, or None (one stage renders every bin).
        scene: the fitted scene (cells, frame, visibility).
        prior: the point-cloud prior Φ, or None.
        stages: ``{"coarse", "fine"}`` (HiTAM) or ``{"fine"}`` rendering stages.
    """

    def __init__(
        self,
        config: RFLSCMConfig,
        angle_grid: AngleGrid,
        hitam: HiTAM | None,
        scene: SceneInfo,
        prior: nn.Module | None,
        stages: nn.ModuleDict,
        device: torch.device,
    ) -> None:
        self.config, self.angle_grid, self.hitam, self.scene = config, angle_grid, hitam, scene
        self.prior, self.stages, self.device = prior, stages, device
        self.cache = RayCache()

    # --- rays ---------------------------------------------------------------------------------
    def _rayset(self, kind: RayKind) -> RaySet:
        if kind not in self.cache.rays:
            hitam = self.hitam
            if kind == "coarse":
                assert hitam is not None, "coarse rays need HiTAM"
                dirs, scale = hitam.coarse_directions(), float(hitam.beta)
            else:
                dirs, scale = self.angle_grid.directions(), 1.0
            g = self.angle_grid
            cos_el = torch.sqrt(dirs[:, 0] ** 2 + dirs[:, 1] ** 2)
            width = torch.clamp(torch.deg2rad(torch.tensor(g.az_step_deg)) * cos_el, min=math.radians(g.el_step_deg))
            self.cache.rays[kind] = RaySet(dirs.to(self.device), (0.5 * scale * width).to(self.device))
        return self.cache.rays[kind]

    def directions(self, kind: RayKind) -> torch.Tensor:
        """Unit vectors ``[num_dirs, 3]`` of the rays of ``kind``."""
        return self._rayset(kind).directions

    def cells(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Cell positions ``[C, 3]`` and wavelengths ``[C]`` on the device (float32)."""
        if self.cache.cells is None:
            xyz = torch.as_tensor(self.scene.cell_xyz, dtype=torch.float32, device=self.device)
            wl = torch.as_tensor(self.scene.wavelength_m, dtype=torch.float32, device=self.device)
            self.cache.cells = (xyz, wl)
        return self.cache.cells

    def ray_samples(self, kind: RayKind) -> RaySet:
        """The rays of ``kind`` with their stored samples (built once): those of the directions each cell sees
        (:meth:`visible`); the others, never rendered, are stored empty (issue 29: about half the directions, so
        half the build time and memory)."""
        rays = self._rayset(kind)
        if rays.samples is None:
            xyz, _ = self.cells()
            frame, cfg = self.scene.frame, self.config
            visible = self.visible(kind).cpu()
            parts = []
            for c in range(xyz.shape[0]):
                seen = torch.nonzero(visible[c]).squeeze(1)
                part = build_ray_samples(
                    xyz[c], rays.directions[seen.to(self.device)], frame.num_samples, cfg.render.step_m, self.prior, 0.0
                )
                parts.append(part.spread(seen, visible.shape[1]))
            rays.samples = RaySamples.concat(parts).to(self.device)
            rays.live = rays.samples.live_counts()
        return rays

    def render(
        self, stage: str, kind: RayKind, cells: torch.Tensor, bins: torch.Tensor, grid_xyz: torch.Tensor
    ) -> torch.Tensor:
        """x̃ ``[Qn]`` (normalised) of rays (cell ``cells[Qn]``, direction ``bins[Qn]``) seen from ``grid_xyz [Qn, 3]``.

        Queries on the same ray share its fields; without gradients the work is chunked to
        ``render.chunk_samples`` decoder evaluations."""
        if cells.numel() == 0:
            return torch.zeros(0, device=self.device)
        rays = self.ray_samples(kind)
        samples, dirs = rays.samples, rays.directions
        assert samples is not None and rays.live is not None
        ray_ids = cells * dirs.shape[0] + bins

        def run(a: int, b: int) -> torch.Tensor:
            unique, inverse = torch.unique(ray_ids[a:b], return_inverse=True)
            xyz, wl = self.cells()
            cell, direction = unique // dirs.shape[0], unique % dirs.shape[0]
            batch = RayBatch(xyz[cell], dirs[direction], wl[cell], rays.radii[direction])
            return self.stages[stage](batch, gather_samples(samples, unique), Queries(inverse, grid_xyz[a:b]))

        if torch.is_grad_enabled():
            return run(0, cells.numel())
        costs = rays.live[ray_ids]
        return chunked(run, chunk_bounds(costs.cpu(), self.config.render.chunk_samples))

    # --- stages ---------------------------------------------------------------------------------
    def visible(self, kind: RayKind) -> torch.Tensor:
        """``[num_cells, num_dirs]`` bool: directions of ``kind`` the cell's round-1 beams see (``render.min_gain_db``)."""
        rays = self._rayset(kind)
        if rays.visible is None:
            fine = torch.as_tensor(self.scene.visible, device=self.device)
            if kind == "coarse":
                assert self.hitam is not None
                children, valid = self.hitam.children.to(self.device), self.hitam.valid.to(self.device)
                fine = (fine[:, children] & valid).any(-1)
            rays.visible = fine
        return rays.visible

    def power_on(
        self,
        stage: str,
        kind: RayKind,
        cells: torch.Tensor,
        grid_xyz: torch.Tensor,
        bins: torch.Tensor,
        valid: torch.Tensor,
    ) -> torch.Tensor:
        """x̃ ``[B, K]`` of pairs (``cells [B]``, ``grid_xyz [B, 3]``) at directions ``bins [B, K]`` of ``kind``,
        rendered where ``valid`` and the cell sees the direction, 0 elsewhere."""
        valid = valid & self.visible(kind)[cells[:, None], bins]
        b, k = valid.nonzero(as_tuple=True)
        x = self.render(stage, kind, cells[b], bins[b, k], grid_xyz[b])
        return x.new_zeros(valid.shape).index_put((b, k), x)

    def coarse_power(self, cells: torch.Tensor, grid_xyz: torch.Tensor) -> torch.Tensor:
        """Coarse APS ``[B, num_coarse]`` of pairs (``cells [B]``, ``grid_xyz [B, 3]``)."""
        assert self.hitam is not None
        bins = torch.arange(self.hitam.num_coarse, device=self.device).expand(cells.numel(), -1)
        return self.power_on("coarse", "coarse", cells, grid_xyz, bins, torch.ones_like(bins, dtype=torch.bool))

    def fine_power(
        self, cells: torch.Tensor, grid_xyz: torch.Tensor, bins: torch.Tensor, valid: torch.Tensor
    ) -> torch.Tensor:
        """Refinement APS ``[B, K]`` at fine ``bins [B, K]`` (0 where not ``valid``)."""
        return self.power_on("fine", "fine", cells, grid_xyz, bins, valid)

    def full_power(self, cells: torch.Tensor, grid_xyz: torch.Tensor) -> torch.Tensor:
        """APS ``[B, num_bins]`` rendered on every bin by one model (w/o HiTAM)."""
        bins = torch.arange(self.angle_grid.num_bins, device=self.device).expand(cells.numel(), -1)
        return self.power_on("fine", "fine", cells, grid_xyz, bins, torch.ones_like(bins, dtype=torch.bool))

    def expand(
        self, cells: torch.Tensor, coarse: torch.Tensor, order: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """HiTAM's Ω′ ``(bins, valid) [B, β² K_C]``: the K_C blocks of largest coarse power among the directions each
        cell sees (the first K_C of ``order``, :meth:`ranking`'s, where given)."""
        h = self.hitam
        assert h is not None
        order = self.ranking(cells, coarse, h.top_k) if order is None else order
        bins, valid = h.refined(order[:, : h.top_k])
        return bins, valid & self.visible("fine")[cells[:, None], bins]

    def ranking(self, cells: torch.Tensor, coarse: torch.Tensor, count: int) -> torch.Tensor:
        """The ``count`` coarse blocks ``[B, count]`` of largest coarse power ``coarse [B, num_coarse]`` among those each
        cell sees, largest first (then blocks the cell does not see, where it sees fewer)."""
        assert self.hitam is not None
        visible = self.visible("coarse")[cells]
        return self.hitam.ranked(torch.where(visible, coarse, torch.full_like(coarse, -1.0)), count)

    def fill(self, cells: torch.Tensor, coarse: torch.Tensor, order: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The coarse fill ``(fine bins, values) [B, β² J]`` outside Ω′ (``hitam.outside: coarse``) of pairs (``cells [B]``,
        coarse APS ``coarse [B, num_coarse]``): the blocks of ``order`` (:meth:`ranking`'s) after its first K_C, each
        one's coarse power spread evenly over its bins the cell sees."""
        h = self.hitam
        assert h is not None
        bins, values, valid = h.spread(coarse, order[:, h.top_k :])  # coarse: 0 at blocks the cell does not see
        seen = valid & self.visible("fine")[cells[:, None], bins]
        return bins, values * seen

    def output(self, cells: torch.Tensor, grid_xyz: torch.Tensor, position: float) -> tuple[torch.Tensor, torch.Tensor]:
        """The model's APS in sparse form ``(fine bins [B, K], values [B, K])`` (normalised) once its latest training
        step began at schedule ``position`` (−1: none): the refinement model's from the warm-up's end on (and the
        coarse fill outside Ω′ with ``hitam.outside: coarse``)."""
        if self.hitam is None:
            x = self.full_power(cells, grid_xyz)
            return torch.arange(x.shape[1], device=self.device).expand_as(x), x
        coarse = self.coarse_power(cells, grid_xyz)
        if position >= self.hitam.warmup_steps:
            filled = self.config.hitam.outside == "coarse"
            order = self.ranking(cells, coarse, self.hitam.top_k * (1 + FILL_BLOCKS if filled else 1))
            bins, valid = self.expand(cells, coarse, order)
            x = self.fine_power(cells, grid_xyz, bins, valid)
            if not filled:
                return bins, x
            fill_bins, fill_x = self.fill(cells, coarse, order)
            return torch.cat([bins, fill_bins], 1), torch.cat([x, fill_x], 1)
        return self.coarse_as_fine(coarse)

    def stage_output(
        self, cells: torch.Tensor, grid_xyz: torch.Tensor, stage: RayKind, position: float
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Sparse APS ``(bins, values)`` of one stage: without HiTAM the output at ``position``; with it the coarse
        APS spread over its blocks (``stage`` "coarse") or the fine APS on the coarse selection ("fine")."""
        if self.hitam is None:
            return self.output(cells, grid_xyz, position)
        coarse = self.coarse_power(cells, grid_xyz)
        if stage == "coarse":
            return self.coarse_as_fine(coarse)
        bins, valid = self.expand(cells, coarse)
        return bins, self.fine_power(cells, grid_xyz, bins, valid)

    def coarse_as_fine(self, coarse: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The coarse APS on fine bins (before the refinement model has trained): a block's power is spread
        evenly over its bins."""
        h = self.hitam
        assert h is not None
        children, valid = h.children.to(self.device), h.valid.to(self.device)
        share = valid / valid.sum(-1, keepdim=True)  # [Nc, β²]
        values = coarse[:, :, None] * share  # [B, Nc, β²]
        return children.flatten().expand(coarse.shape[0], -1), values.flatten(1)


@dataclass
class TrainContext:
    """Training-only tensors: pair data, normalised A (full and coarse columns) and HiTAM's frozen selection."""

    data: PairData
    a_norm: torch.Tensor
    a_coarse: torch.Tensor | None
    num_ssb: int
    """Columns ``0 … num_ssb−1`` of the stacked sensing matrix are SSB beams, the rest CSI-RS beams."""
    selection: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
    """``(bins, valid, known)`` of every training pair once α = 1 (see :meth:`~rflscm.models.rflscm.RFLSCM._frozen_selection`)."""

    def columns(self, cells: torch.Tensor, bins: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """Normalised A columns ``[B, M, K]`` of fine ``bins [B, K]`` (zeroed where not ``valid``)."""
        a = self.a_norm
        beams = torch.arange(a.shape[1], device=a.device)
        cols = a[cells[:, None, None], beams[None, :, None], bins[:, None, :]]
        return cols if valid is None else cols * valid[:, None, :].to(cols.dtype)
