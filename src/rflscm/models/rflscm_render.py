"""Rendering, HiTAM and losses of radiance-field LSCM models (mixed into :class:`RFLSCM`).

Rays are identified by (cell, direction): ``kind="coarse"`` uses HiTAM's coarse directions,
``kind="fine"`` the angle grid's bins.  Their stored samples (Φ > 0 plus FDAM neighbours) are
computed once per cell and kept (:func:`rflscm.render.build_ray_samples`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from rflscm.models.radiance import Queries, RayBatch
from rflscm.render import RaySamples, build_ray_samples, chunk_bounds, chunked, gather_samples
from rflscm.train.losses import lscm_loss, mae_db

PAIR_CHUNK = 64  # pairs per inference chunk (A columns and APS rows stay small)


class RenderMixin:
    """Needs ``config``, ``scene``, ``prior``, ``stages``, ``hitam``, ``angle_grid``, ``device``, ``step``, ``_cache``, ``_train``."""

    # --- rays ---------------------------------------------------------------------------------
    def _directions(self, kind: str) -> torch.Tensor:
        """Unit vectors ``[num_dirs, 3]`` of the rays of ``kind`` (their cone radii: :meth:`_radii`)."""
        key = f"dirs_{kind}"
        if key not in self._cache:
            dirs = self.hitam.coarse_directions() if kind == "coarse" else self.angle_grid.directions()
            self._cache[key] = dirs.to(self.device)
            scale = self.hitam.beta if kind == "coarse" else 1
            g = self.angle_grid
            cos_el = torch.sqrt(dirs[:, 0] ** 2 + dirs[:, 1] ** 2)
            width = torch.clamp(torch.deg2rad(torch.tensor(g.az_step_deg)) * cos_el, min=math.radians(g.el_step_deg))
            self._cache[f"radii_{kind}"] = (0.5 * scale * width).to(self.device)
        return self._cache[key]

    def _cells(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Cell positions ``[C, 3]`` and wavelengths ``[C]`` on the device (float32)."""
        if "cells" not in self._cache:
            xyz = torch.as_tensor(self.scene.cell_xyz, dtype=torch.float32, device=self.device)
            wl = torch.as_tensor(self.scene.wavelength_m, dtype=torch.float32, device=self.device)
            self._cache["cells"] = (xyz, wl)
        return self._cache["cells"]

    def _ray_samples(self, kind: str) -> RaySamples:
        """Stored samples of every (cell, direction) ray of ``kind``, built once."""
        key = f"rays_{kind}"
        if key not in self._cache:
            dirs, (xyz, _) = self._directions(kind), self._cells()
            frame, cfg = self.scene.frame, self.config
            parts = [
                build_ray_samples(xyz[c], dirs, frame.num_samples, cfg.render.step_m, self.prior, cfg.prior.skip_below)
                for c in range(xyz.shape[0])
            ]
            self._cache[key] = RaySamples.concat(parts).to(self.device)
            self._cache[f"live_{kind}"] = self._cache[key].live_counts()
        return self._cache[key]

    def _render(self, stage: str, kind: str, cells: torch.Tensor, bins: torch.Tensor, grid_xyz: torch.Tensor) -> torch.Tensor:
        """x̃ ``[Qn]`` (normalised) of rays (cell ``cells[Qn]``, direction ``bins[Qn]``) seen from ``grid_xyz [Qn, 3]``.

        Queries on the same ray share its fields; without gradients the work is chunked to
        ``render.chunk_samples`` decoder evaluations."""
        if cells.numel() == 0:
            return torch.zeros(0, device=self.device)
        samples, dirs = self._ray_samples(kind), self._directions(kind)
        ray_ids = cells * dirs.shape[0] + bins

        def run(a: int, b: int) -> torch.Tensor:
            rays, inverse = torch.unique(ray_ids[a:b], return_inverse=True)
            xyz, wl = self._cells()
            cell, direction = rays // dirs.shape[0], rays % dirs.shape[0]
            batch = RayBatch(xyz[cell], dirs[direction], wl[cell], self._cache[f"radii_{kind}"][direction])
            return self.stages[stage](batch, gather_samples(samples, rays), Queries(inverse, grid_xyz[a:b]))

        if torch.is_grad_enabled():
            return run(0, cells.numel())
        costs = self._cache[f"live_{kind}"][ray_ids]
        return chunked(run, chunk_bounds(costs.cpu(), self.config.render.chunk_samples))

    # --- stages ---------------------------------------------------------------------------------
    def _visible(self, kind: str) -> torch.Tensor:
        """``[num_cells, num_dirs]`` bool: directions of ``kind`` the cell's round-1 beams see (``render.min_gain_db``)."""
        key = f"visible_{kind}"
        if key not in self._cache:
            fine = torch.as_tensor(self.scene.visible, device=self.device)
            if kind == "coarse":
                children, valid = self.hitam.children.to(self.device), self.hitam.valid.to(self.device)
                fine = (fine[:, children] & valid).any(-1)
            self._cache[key] = fine
        return self._cache[key]

    def _power_on(self, stage: str, kind: str, cells: torch.Tensor, grid_xyz: torch.Tensor,
                  bins: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:  # fmt: skip
        """x̃ ``[B, K]`` of pairs (``cells [B]``, ``grid_xyz [B, 3]``) at directions ``bins [B, K]`` of ``kind``,
        rendered where ``valid`` and the cell sees the direction, 0 elsewhere."""
        valid = valid & self._visible(kind)[cells[:, None], bins]
        b, k = valid.nonzero(as_tuple=True)
        x = self._render(stage, kind, cells[b], bins[b, k], grid_xyz[b])
        return x.new_zeros(valid.shape).index_put((b, k), x)

    def _coarse_power(self, cells: torch.Tensor, grid_xyz: torch.Tensor) -> torch.Tensor:
        """Coarse APS ``[B, num_coarse]`` of pairs (``cells [B]``, ``grid_xyz [B, 3]``)."""
        bins = torch.arange(self.hitam.num_coarse, device=self.device).expand(cells.numel(), -1)
        return self._power_on("coarse", "coarse", cells, grid_xyz, bins, torch.ones_like(bins, dtype=torch.bool))

    def _fine_power(self, cells: torch.Tensor, grid_xyz: torch.Tensor, bins: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """Refinement APS ``[B, K]`` at fine ``bins [B, K]`` (0 where not ``valid``)."""
        return self._power_on("fine", "fine", cells, grid_xyz, bins, valid)

    def _full_power(self, cells: torch.Tensor, grid_xyz: torch.Tensor) -> torch.Tensor:
        """APS ``[B, num_bins]`` rendered on every bin by one model (w/o HiTAM)."""
        bins = torch.arange(self.angle_grid.num_bins, device=self.device).expand(cells.numel(), -1)
        return self._power_on("fine", "fine", cells, grid_xyz, bins, torch.ones_like(bins, dtype=torch.bool))

    def _expand(self, cells: torch.Tensor, coarse: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """HiTAM's Ω′ ``(bins, valid) [B, β² K_C]`` among the directions each cell sees."""
        visible = self._visible("coarse")[cells]
        bins, valid = self.hitam.expand(torch.where(visible, coarse, torch.full_like(coarse, -1.0)))
        return bins, valid & self._visible("fine")[cells[:, None], bins]

    def _output(self, cells: torch.Tensor, grid_xyz: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The model's APS in sparse form ``(fine bins [B, K], values [B, K])`` (normalised)."""
        if self.hitam is None:
            x = self._full_power(cells, grid_xyz)
            return torch.arange(x.shape[1], device=self.device).expand_as(x), x
        coarse = self._coarse_power(cells, grid_xyz)
        if self.step > self.hitam.warmup_steps:
            bins, valid = self._expand(cells, coarse)
            return bins, self._fine_power(cells, grid_xyz, bins, valid)
        return self._coarse_as_fine(coarse)

    def _coarse_as_fine(self, coarse: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The coarse APS on fine bins (before the refinement model has trained): a block's power is spread
        evenly over its bins (``block``) or put on its representative bin (paper form)."""
        h = self.hitam
        if h.coarse_bins == "representative":
            return h.mapping.representative_bins().to(self.device).expand_as(coarse), coarse
        children, valid = h.children.to(self.device), h.valid.to(self.device)
        share = valid / valid.sum(-1, keepdim=True)  # [Nc, β²]
        values = coarse[:, :, None] * share  # [B, Nc, β²]
        return children.flatten().expand(coarse.shape[0], -1), values.flatten(1)

    # --- losses ---------------------------------------------------------------------------------
    def _loss(self, a_sel: torch.Tensor, x: torch.Tensor, pairs: torch.Tensor) -> dict[str, torch.Tensor]:
        d, c = self._train.data, self.config.loss
        pred = torch.einsum("bmk,bk->bm", a_sel, x)
        return lscm_loss(
            pred, d.rsrp[pairs], d.beam_mask[pairs], x, d.x_scale[pairs], d.bound[pairs],
            c.fidelity, c.sparsity, c.missing_penalty, floor=10.0 ** (c.floor_db / 10.0),
        )  # fmt: skip

    def _columns(self, cells: torch.Tensor, bins: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """Normalised A columns ``[B, M, K]`` of fine ``bins [B, K]`` (zeroed where not ``valid``)."""
        a = self._train.a_norm
        beams = torch.arange(a.shape[1], device=a.device)
        cols = a[cells[:, None, None], beams[None, :, None], bins[:, None, :]]
        return cols if valid is None else cols * valid[:, None, :].to(cols.dtype)

    def training_losses(self, pairs: torch.Tensor, step: int) -> dict[str, Any]:
        """HiTAM loss (1 − α) L⁽¹⁾ + α L⁽²⁾ of a batch of pair indices ``pairs [B]``."""
        d = self._train.data
        pairs = pairs.to(self.device)
        cells, xyz = d.cell_index[pairs], d.grid_xyz[pairs]
        if self.hitam is None:
            return self._loss(self._train.a_norm[cells], self._full_power(cells, xyz), pairs)
        alpha = self.hitam.alpha(step)
        out: dict[str, Any] = {"alpha": alpha}
        total = 0.0
        if alpha < 1.0:
            coarse = self._coarse_power(cells, xyz)
            l1 = self._loss(self._train.a_coarse[cells], coarse, pairs)
            total = total + (1.0 - alpha) * l1["total"]
            out.update({"coarse": l1["total"], **{k: v for k, v in l1.items() if k != "total"}})
            bins, valid = self._expand(cells, coarse.detach())
        else:
            bins, valid = self._frozen_selection(pairs)
        if alpha > 0.0:
            l2 = self._loss(self._columns(cells, bins, valid), self._fine_power(cells, xyz, bins, valid), pairs)
            total = total + alpha * l2["total"]
            out.update({"fine": l2["total"], **{k: v for k, v in l2.items() if k != "total"}})
        out["total"] = total
        return out

    @torch.no_grad()
    def _frozen_selection(self, pairs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """HiTAM's Ω′ of training ``pairs [B]`` once α = 1: the coarse model no longer trains, so each pair's
        selection is rendered once and remembered (until the weights are replaced, see :meth:`forget_aps`)."""
        d = self._train.data
        memo = self._cache.get("selection")
        if memo is None:
            width = self.hitam.top_k * self.hitam.beta**2
            memo = (torch.zeros(d.num_pairs, width, dtype=torch.long, device=self.device),
                    torch.zeros(d.num_pairs, width, dtype=torch.bool, device=self.device),
                    torch.zeros(d.num_pairs, dtype=torch.bool, device=self.device))  # fmt: skip
            self._cache["selection"] = memo
        bins, valid, known = memo
        todo = pairs[~known[pairs]].unique()
        if todo.numel():
            cells = d.cell_index[todo]
            bins[todo], valid[todo] = self._expand(cells, self._coarse_power(cells, d.grid_xyz[todo]))
            known[todo] = True
        return bins[pairs], valid[pairs]

    @torch.no_grad()
    def _median_error_db(self, stage: str, num_pairs: int = 64) -> float:
        """Median (prediction − measurement) [dB] of ``stage``'s APS over the observed beams of a few training pairs."""
        d = self._train.data
        pairs = torch.arange(d.num_pairs, device=self.device)[:: max(1, d.num_pairs // num_pairs)][:num_pairs]
        cells, xyz = d.cell_index[pairs], d.grid_xyz[pairs]
        if self.hitam is None:
            bins, values = self._output(cells, xyz)
        elif stage == "coarse":
            bins, values = self._coarse_as_fine(self._coarse_power(cells, xyz))
        else:
            bins, valid = self._expand(cells, self._coarse_power(cells, xyz))
            values = self._fine_power(cells, xyz, bins, valid)
        pred = torch.einsum("bmk,bk->bm", self._columns(cells, bins), values)
        observed = d.beam_mask[pairs] & ~torch.isnan(d.rsrp[pairs])
        diff = 10.0 * torch.log10(pred[observed].clamp_min(1e-30) / d.rsrp[pairs][observed])
        return float(diff.median())

    @torch.no_grad()
    def _calibrate_level(self, target_db: float) -> float:
        """Rescale every stage's radiance so that the median (prediction − measurement) is ``target_db``;
        returns the shift applied [dB]."""
        shift = target_db - self._median_error_db("coarse" if self.hitam is not None else "fine")
        for stage in self.stages.values():
            stage.decoder.scale_power(10.0 ** (shift / 10.0))
        return shift

    @torch.no_grad()
    def _match_fine_to_coarse(self) -> float:
        """Rescale the refinement model so that its median error equals the coarse model's (the hand-over
        after a copy: fine rays have narrower cones, so β² children do not sum to their block); returns dB."""
        shift = self._median_error_db("coarse") - self._median_error_db("fine")
        self.stages["fine"].decoder.scale_power(10.0 ** (shift / 10.0))
        return shift

    @torch.no_grad()
    def validation_mae(self) -> float:
        """MAE [dB] on the held-aside round-1 beams (NaN without any)."""
        d = self._train.data
        if d.val_pairs.numel() == 0:
            return float("nan")
        errs, counts = [], []
        for start in range(0, d.val_pairs.numel(), PAIR_CHUNK):
            pairs = d.val_pairs[start : start + PAIR_CHUNK]
            cells = d.cell_index[pairs]
            bins, values = self._output(cells, d.grid_xyz[pairs])
            pred = torch.einsum("bmk,bk->bm", self._columns(cells, bins), values)
            mask = d.val_mask[pairs]
            count = int((mask & ~torch.isnan(d.rsrp[pairs])).sum())
            if count:
                errs.append(float(mae_db(pred, d.rsrp[pairs], mask)) * count)
                counts.append(count)
        return sum(errs) / sum(counts) if counts else float("nan")

    # --- the contract's APS ---------------------------------------------------------------------
    @torch.no_grad()
    def aps(self, cell_ids: np.ndarray, grid_ids: np.ndarray, grid_xyz: np.ndarray | None = None) -> torch.Tensor:
        """APS ``[num_pairs, num_bins]`` [linear path gain] (see :meth:`LSCMModel.aps`).

        Rendered APS are remembered (sparse) per (cell, grid position) until the weights change, so
        that predicting SSB and CSI-RS RSRP of the same pairs renders them once."""
        if self.scene is None:
            raise RuntimeError("the model has not been fitted")
        cells = self.scene.cell_index(cell_ids)
        xyz = self.scene.grid_positions(grid_ids) if grid_xyz is None else np.asarray(grid_xyz, np.float64).reshape(-1, 3)
        memo = self._cache.setdefault("aps_memo", {})
        keys = [(int(c), *np.round(p, 3).tolist()) for c, p in zip(cells, xyz)]
        todo = sorted({i for i, k in enumerate(keys) if k not in memo}, key=lambda i: (keys[i][0], i))
        for start in range(0, len(todo), PAIR_CHUNK):
            rows = todo[start : start + PAIR_CHUNK]
            c = torch.as_tensor(cells[rows], device=self.device)
            g = torch.as_tensor(xyz[rows], dtype=torch.float32, device=self.device)
            bins, values = self._output(c, g)
            for j, i in enumerate(rows):
                memo[keys[i]] = (bins[j], values[j])
        out = torch.zeros(len(keys), self.angle_grid.num_bins, device=self.device)
        if keys:
            bins = torch.stack([memo[k][0] for k in keys])
            values = torch.stack([memo[k][1] for k in keys])
            out.scatter_add_(1, bins, values)
        return out * self.scene.x_ref

    def forget_aps(self) -> None:
        """Drop remembered APS (after the weights changed)."""
        self._cache.pop("aps_memo", None)
