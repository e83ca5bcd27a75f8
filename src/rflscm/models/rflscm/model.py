"""RF-LSCM: the radiance-field localized statistical channel model (paper §III–IV, SPEC §3).

``RFLSCM`` implements the model contract (:mod:`rflscm.models.base`).  It owns HiTAM, the
training data and the losses; it composes an :class:`~rflscm.models.rflscm.renderer.APSRenderer`
(rays, visibility, HiTAM's selection; no parameters) over its rendering stages
(:class:`~rflscm.models.rflscm.fields.RadianceStage`: fields and decoder).  The fields come from the
:class:`~rflscm.models.rflscm.fields.FieldFactory` given at construction — the one seam through which
NeRF²-LSCM plugs in MLP fields instead of VM tensors and reuses everything else.

Units: the stages render the APS in the normalised unit x_ref = r_ref / a_ref (see
:mod:`rflscm.models.pairs`); :meth:`aps` returns linear path gain.  Training is driven from above by
the trainer's ``fit`` (package ``train``) through the trainer's ``Trainable``
protocol (``prepare``, ``training_losses``, …); the trainer owns the step count, the optimizer and
its state; the model sees each step's schedule ``position`` only.

The decisions where the paper is silent are listed in the package docstring (:mod:`rflscm.models.rflscm`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, cast

import numpy as np
import pandas as pd
import torch
from torch import nn

from rflscm.data import BEAM_TYPES
from rflscm.data.reporting import rule_of
from rflscm.fields import PassiveMedium, TensorVM
from rflscm.fields.point_prior import PointPrior
from rflscm.fields.surfaces import SurfaceOrientation
from rflscm.geometry import AngleGrid
from rflscm.models.base import FreshPairs, LSCMModel, PassCost, TrainingPlan, register_model
from rflscm.models.pairs import build_pair_data, reference_power, stacked_sensing
from rflscm.models.rflscm import checkpoint
from rflscm.models.rflscm.config import (
    FLOOR_DB,
    INIT_LEVEL_DB,
    INIT_LOSS_DB,
    LEARN_MU,
    SPARSITY,
    VAL_BEAM_FRACTION,
    RFLSCMConfig,
    TrainConfig,
    load_rflscm_config,
)
from rflscm.models.rflscm.corrections import (
    BLEND_REACH,
    PAIR_CHUNK,
    UNSEEN_WEIGHT,
    PairCorrections,
    PassTimes,
    RoundOneCensor,
    TimeLeftFn,
    blend_grids,
    choose_blend,
    fit_corrections,
    measure_pass,
)
from rflscm.models.rflscm.fields import (
    FieldFactory,
    RadianceDecoder,
    RadianceStage,
    SceneFrame,
    VMFieldFactory,
    fit_loss_channel,
)
from rflscm.models.rflscm.hitam import HiTAM
from rflscm.models.rflscm.losses import lscm_loss, mae_db
from rflscm.models.rflscm.renderer import APSRenderer, RayKind, TrainContext
from rflscm.models.rflscm.scene import (
    SceneInfo,
    building_targets,
    check_scene_box,
    make_frame,
    make_prior,
    make_surfaces,
    scene_box,
    visible_bins,
)
from rflscm.models.source import RsrpMix

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario

FRESH_PAIRS = 128
"""Pairs of a caller's fresh pairs rendered, in their calls' chunks, at each measurement of the pass
(:meth:`RFLSCM._fresh_render_s`): on the 222-cell city the evaluation's chunks are one cell's 5–10 pairs, about 30 ms
each, and a full one of 64 takes about 0.2 s, so about 0.5 s either way."""
FRESH_CHUNKS = 16
"""At most this many chunks are timed (and at least two), whatever their size."""


@register_model
class RFLSCM(LSCMModel):
    """RF-LSCM with VM-tensor fields, FDAM, the point-cloud prior and HiTAM."""

    name: ClassVar[str] = "rflscm"
    config_class: ClassVar[type] = RFLSCMConfig
    config_family: ClassVar[str] = "rflscm"
    init_fit: ClassVar[tuple[int, float]] = (50, 0.2)
    """Adam steps and learning rate of the attenuation initialisation (:meth:`_init_attenuation`): for the VM
    tensors a closer fit than 100 steps at 0.05 in half the time, on both scenes measured
    (``scripts/attenuation_init_probe.py``)."""

    def __init__(
        self,
        config: RFLSCMConfig,
        angle_grid: AngleGrid,
        device: torch.device | str = "cpu",
        fields: FieldFactory | None = None,
    ) -> None:
        """``fields`` builds each stage's fields (default: RF-LSCM's VM tensors from ``config.field``)."""
        super().__init__(angle_grid, device)
        self.config = config
        self.fields: FieldFactory = fields if fields is not None else VMFieldFactory(config.field)
        h = config.hitam
        self.hitam = HiTAM(angle_grid, h.beta, h.top_k, h.warmup_steps, h.ramp_steps) if h.enabled else None
        self.scene: SceneInfo | None = None
        self.prior: PointPrior | None = None
        self.surfaces: SurfaceOrientation | None = None
        """The scan's surface orientation (decoder's specular cue), or None."""
        self.stages = nn.ModuleDict()
        self.position = -1.0
        """Schedule position of the latest training step begun (units of ``train.steps``, see the trainer's
        ``Trainable``, which owns the step count; −1 before the first).  HiTAM and upsampling follow it."""
        self.renderer: APSRenderer | None = None
        """Built with the stages (fit or checkpoint)."""
        self.corrections = PairCorrections()
        """The post-training pair corrections (fitted in :meth:`finish_training`, applied in :meth:`aps`)."""
        self._train: TrainContext | None = None
        self._silence_dbm: float | None = None  # round 1's SSB bound for a wholly unreported pair (None: rule sinr)
        self._blend_grids = np.zeros(0, np.int64)
        self._pass_times: PassTimes | None = None  # the pass's latest measured cost (finish_seconds), which sizes it
        """Training grids held out of the field's training to choose the unseen-grid blend (``unseen_blend_grids``)."""

    @classmethod
    def build(
        cls,
        config: str | Path | dict[str, Any] | None = None,
        angle_grid: AngleGrid | None = None,
        device: torch.device | str = "cpu",
    ) -> RFLSCM:
        """A fresh model from a preset (``"quick"``, ``"full"``), a YAML path, a mapping or ``None``."""
        return cls(load_rflscm_config(config, cls.config_class, cls.config_family), angle_grid or AngleGrid(), device)

    # --- construction ---------------------------------------------------------------------------
    def medium(self, frame: SceneFrame) -> PassiveMedium:
        return PassiveMedium(frame.reference_wavelength_m, self.config.render.step_m, LEARN_MU, INIT_LOSS_DB)

    def _build_stages(self, frame: SceneFrame) -> None:
        """Fresh stages (``coarse`` and ``fine`` with HiTAM, else ``fine``) and the renderer over them."""

        def stage() -> RadianceStage:
            fields = self.fields(frame, self.medium(frame).num_channels)
            cfg = self.config
            decoder = RadianceDecoder(
                cfg.decoder, fields.feature_dim, frame, cfg.render.step_m, self.fields.head_hidden
            )
            return RadianceStage(fields, self.medium(frame), decoder, cfg.render, self.surfaces)

        names = ("coarse", "fine") if self.hitam is not None else ("fine",)
        self.stages = nn.ModuleDict({n: stage() for n in names}).to(self.device)
        assert self.scene is not None
        self.renderer = APSRenderer(
            self.config, self.angle_grid, self.hitam, self.scene, self.prior, self.stages, self.device
        )

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """``{"tensors": VM vectors, matrices and basis vectors, "networks": the decoders}``
        (empty groups dropped)."""
        groups: dict[str, list[nn.Parameter]] = {"tensors": [], "networks": []}
        for module in self.stages.modules():
            if isinstance(module, TensorVM):
                groups["tensors"].extend(module.parameters())
        tensor_ids = {id(p) for p in groups["tensors"]}
        groups["networks"] = [p for p in self.stages.parameters() if id(p) not in tensor_ids]
        return {k: v for k, v in groups.items() if v}

    # --- fitting ------------------------------------------------------------------------------
    def _prepare(self, scenario: Scenario) -> None:
        """Scene facts, normalisation, prior, fresh stages and training data for ``scenario``."""
        cfg = self.config
        torch.manual_seed(cfg.train.seed)
        cell_ids = scenario.cell_ids()
        a_mw, num_ssb = stacked_sensing(scenario, cell_ids, self.angle_grid, device=self.device)
        a_ref = float(a_mw.flatten(1).max(1).values.median())
        r_ref = reference_power(np.concatenate([scenario.rsrp_table(1, t)[1].ravel() for t in BEAM_TYPES]))
        a_norm = a_mw / a_ref
        data = build_pair_data(
            scenario, cell_ids, a_norm, num_ssb, r_ref, cfg.train.val_pairs, VAL_BEAM_FRACTION, cfg.train.seed
        )
        cell_xyz = np.stack([scenario.cell_position(int(c)) for c in cell_ids])
        wavelengths = np.array([scenario.wavelength_m(int(c)) for c in cell_ids])
        dist = np.linalg.norm(data.grid_xyz.double().numpy() - cell_xyz[data.cell_index.numpy()], axis=1)
        lo, hi = scene_box(scenario, cfg.render.step_m)
        check_scene_box(cfg, lo, hi)
        grids = scenario.grids
        self.scene = SceneInfo(
            cell_ids,
            cell_xyz,
            wavelengths,
            grids["grid_id"].to_numpy(np.int64),
            grids[["x", "y", "z"]].to_numpy(np.float64),
            r_ref,
            a_ref,
            make_frame(cfg, lo, hi, cell_xyz, wavelengths, dist),
            visible_bins(a_mw, cfg.render.min_gain_db),
        )
        prior = make_prior(cfg, scenario, lo, hi)
        self.prior = prior.to(self.device) if prior is not None else None
        surfaces = make_surfaces(scenario, lo, hi, seed=cfg.train.seed)
        self.surfaces = surfaces.to(self.device) if surfaces is not None else None
        self._build_stages(self.scene.frame)
        targets = building_targets(cfg, scenario, prior, seed=cfg.train.seed) if prior is not None else None
        if targets is not None:
            self._init_attenuation(*targets)
        a_coarse = self.hitam.coarse_columns(a_norm) if self.hitam is not None else None
        self._train = TrainContext(data.to(self.device), a_norm, a_coarse, num_ssb)
        ssb_rule = rule_of(scenario, "ssb").rule
        self._silence_dbm = None if ssb_rule == "sinr" else float(scenario.meta.rsrp_threshold_dbm)
        self.corrections = PairCorrections()
        self.position = -1.0
        self._calibrate_level(INIT_LEVEL_DB)

    @property
    def train_config(self) -> TrainConfig:
        return self.config.train

    def prepare(self, scenario: Scenario) -> TrainingPlan:
        """Fresh weights and training data for ``scenario``; the training pairs (those with a training beam),
        grouped by cell (see the trainer's ``Trainable`` protocol)."""
        self._prepare(scenario)
        d = self._training().data
        self.run_info["num_pairs"] = d.num_pairs
        trained = d.beam_mask.any(1)
        self._blend_grids = blend_grids(d, self.config.corrections.unseen_blend_grids or 0.0, self.config.train.seed)
        if self._blend_grids.size:  # their reports choose the unseen-grid blend after training: not trained on
            trained = trained & torch.as_tensor(~np.isin(d.grid_ids, self._blend_grids), device=trained.device)
        pairs = torch.nonzero(trained).squeeze(1).cpu()
        return TrainingPlan(pairs, d.cell_index.cpu()[pairs])

    def resume_from(self, payload: dict[str, Any], path: str | Path) -> None:
        """Load weights and schedule position from the checkpoint ``payload`` of ``path`` (see
        :func:`~rflscm.models.rflscm.checkpoint.check_resume`)."""
        state = checkpoint.check_resume(self, payload, path)
        self._load_stage_weights(state["stages"])
        self.position = float(state["position"])

    def _init_attenuation(self, points: torch.Tensor, share: torch.Tensor) -> None:
        """Fit the δ field so that its per-voxel loss is ``building_loss_db`` to the power ``share`` times
        ``INIT_LOSS_DB`` to the power 1 − ``share`` (log-linear: free space where ``share`` = 0), other
        channels unchanged; every stage starts from the same fit."""
        f = self.config.field
        points, share = points.to(self.device), share.to(self.device)
        assert f.building_loss_db is not None
        target = share * math.log(f.building_loss_db / INIT_LOSS_DB)  # raw loss channel
        stages = self.all_stages()
        fields = stages[0].fields
        with torch.no_grad():
            keep = fields.delta(fields.encode(points))[:, 1:]
        fit_loss_channel(fields, points, target, keep, *self.init_fit)
        for stage in stages[1:]:
            stage.fields.delta_module().load_state_dict(fields.delta_module().state_dict())

    def on_step_begin(self, step: int, position: float) -> bool:
        """Begin step ``step`` at schedule ``position``: upsample the tensors when the position crosses an
        ``upsample_at`` step, hand the coarse model to the refinement model when it crosses the end of the
        HiTAM warm-up (previous step's position < threshold <= ``position``; in step mode: ``step`` equals the
        threshold).  True when parameters were replaced."""
        before, self.position = self.position, position
        h = self.config.hitam
        if self.hitam is not None and before < float(h.warmup_steps) <= position and position > 0:
            self.stages["fine"].load_state_dict(self.stages["coarse"].state_dict())
            self._match_fine_to_coarse()
        levels = [i + 1 for i, at in enumerate(self.fields.upsample_at) if before < at <= position]
        if not levels:
            return False
        assert self.scene is not None and self._train is not None
        self._train.selection = None
        for level in levels:  # a budget step may cross several
            res = self.fields.resolution(self.scene.frame, level)
            for module in self.stages.modules():
                if isinstance(module, TensorVM) and res is not None:
                    module.upsample(res)
        return True

    def decoder_evals(self) -> int:
        """Radiance-decoder evaluations so far (all stages)."""
        return sum(s.decoder_evals for s in self.all_stages())

    def stage(self, name: str) -> RadianceStage:
        """The rendering stage ``name`` (``"coarse"`` or ``"fine"``)."""
        return cast(RadianceStage, self.stages[name])

    def all_stages(self) -> list[RadianceStage]:
        return [cast(RadianceStage, s) for s in self.stages.values()]

    def _training(self) -> TrainContext:
        if self._train is None:
            raise RuntimeError("the model has no training data; fit it first.")
        return self._train

    def _renderer(self) -> APSRenderer:
        if self.renderer is None:
            raise RuntimeError("the model has not been fitted")
        return self.renderer

    # --- losses ---------------------------------------------------------------------------------
    def _loss(self, a_sel: torch.Tensor, x: torch.Tensor, pairs: torch.Tensor) -> dict[str, torch.Tensor]:
        d, c = self._training().data, self.config.loss
        pred = torch.einsum("bmk,bk->bm", a_sel, x)
        return lscm_loss(
            pred,
            d.rsrp[pairs],
            d.beam_mask[pairs],
            x,
            d.x_scale[pairs],
            d.bound[pairs],
            c.fidelity,
            SPARSITY,
            c.missing_penalty,
            floor=10.0 ** (FLOOR_DB / 10.0),
        )

    def training_losses(self, pairs: torch.Tensor, position: float) -> dict[str, Any]:
        """HiTAM loss (1 − α) L⁽¹⁾ + α L⁽²⁾ of a batch of pair indices ``pairs [B]``, α at schedule ``position``."""
        d = self._training().data
        pairs = pairs.to(self.device)
        cells, xyz = d.cell_index[pairs], d.grid_xyz[pairs]
        if self.hitam is None:
            return self._loss(self._training().a_norm[cells], self._renderer().full_power(cells, xyz), pairs)
        alpha = self.hitam.alpha(position)
        out: dict[str, Any] = {"alpha": alpha}
        total: torch.Tensor | float = 0.0
        if alpha < 1.0:
            coarse = self._renderer().coarse_power(cells, xyz)
            a_coarse = self._training().a_coarse
            assert a_coarse is not None
            l1 = self._loss(a_coarse[cells], coarse, pairs)
            total = total + (1.0 - alpha) * l1["total"]
            out.update({"coarse": l1["total"], **{k: v for k, v in l1.items() if k != "total"}})
            bins, valid = self._renderer().expand(cells, coarse.detach())
        else:
            bins, valid = self._frozen_selection(pairs)
        if alpha > 0.0:
            l2 = self._loss(
                self._training().columns(cells, bins, valid),
                self._renderer().fine_power(cells, xyz, bins, valid),
                pairs,
            )
            total = total + alpha * l2["total"]
            out.update({"fine": l2["total"], **{k: v for k, v in l2.items() if k != "total"}})
        out["total"] = total
        return out

    @torch.no_grad()
    def _frozen_selection(self, pairs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """HiTAM's Ω′ of training ``pairs [B]`` once α = 1: the coarse model no longer trains, so each pair's
        selection is rendered once and remembered (until the weights are replaced)."""
        train, hitam = self._training(), self.hitam
        assert hitam is not None
        d, memo = train.data, train.selection
        if memo is None:
            width = hitam.top_k * hitam.beta**2
            memo = (
                torch.zeros(d.num_pairs, width, dtype=torch.long, device=self.device),
                torch.zeros(d.num_pairs, width, dtype=torch.bool, device=self.device),
                torch.zeros(d.num_pairs, dtype=torch.bool, device=self.device),
            )
            train.selection = memo
        bins, valid, known = memo
        todo = pairs[~known[pairs]].unique()
        if todo.numel():
            cells = d.cell_index[todo]
            bins[todo], valid[todo] = self._renderer().expand(
                cells, self._renderer().coarse_power(cells, d.grid_xyz[todo])
            )
            known[todo] = True
        return bins[pairs], valid[pairs]

    @torch.no_grad()
    def _median_error_db(self, stage: RayKind, num_pairs: int = 64) -> float:
        """Median (prediction − measurement) [dB] of ``stage``'s APS over the observed beams of a few training pairs."""
        d = self._training().data
        pairs = torch.arange(d.num_pairs, device=self.device)[:: max(1, d.num_pairs // num_pairs)][:num_pairs]
        cells, xyz = d.cell_index[pairs], d.grid_xyz[pairs]
        bins, values = self._renderer().stage_output(cells, xyz, stage, self.position)
        pred = torch.einsum("bmk,bk->bm", self._training().columns(cells, bins), values)
        observed = d.observed[pairs]
        diff = 10.0 * torch.log10(pred[observed].clamp_min(1e-30) / d.rsrp[pairs][observed])
        return float(diff.median())

    @torch.no_grad()
    def _calibrate_level(self, target_db: float) -> float:
        """Rescale every stage's radiance so that the median (prediction − measurement) is ``target_db``;
        returns the shift applied [dB]."""
        shift = target_db - self._median_error_db("coarse" if self.hitam is not None else "fine")
        for stage in self.all_stages():
            stage.decoder.scale_power(10.0 ** (shift / 10.0))
        return shift

    @torch.no_grad()
    def _match_fine_to_coarse(self) -> float:
        """Rescale the refinement model so that its median error equals the coarse model's (the hand-over
        after a copy: fine rays have narrower cones, so β² children do not sum to their block); returns dB."""
        shift = self._median_error_db("coarse") - self._median_error_db("fine")
        self.stage("fine").decoder.scale_power(10.0 ** (shift / 10.0))
        return shift

    @torch.no_grad()
    def validation_mae(self) -> float:
        """MAE [dB] on the held-aside round-1 beams (NaN without any)."""
        d = self._training().data
        if d.val_pairs.numel() == 0:
            return float("nan")
        errs, counts = [], []
        for start in range(0, d.val_pairs.numel(), PAIR_CHUNK):
            pairs = d.val_pairs[start : start + PAIR_CHUNK]
            cells = d.cell_index[pairs]
            bins, values = self._renderer().output(cells, d.grid_xyz[pairs], self.position)
            pred = torch.einsum("bmk,bk->bm", self._training().columns(cells, bins), values)
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

        Each distinct (cell, grid position) of the call is rendered once; evaluation and the benchmarks
        remember rendered APS across calls (:class:`rflscm.eval.cache.APSCache`)."""
        if self.scene is None or self.renderer is None:
            raise RuntimeError("the model has not been fitted")
        R = self.renderer
        cells = self.scene.cell_index(cell_ids)
        xyz = (
            self.scene.grid_positions(grid_ids) if grid_xyz is None else np.asarray(grid_xyz, np.float64).reshape(-1, 3)
        )
        skip = self.corrections.unrendered(cell_ids, grid_ids)  # answered whole by the corrections: not rendered
        # the pairs the pass corrected, asked at their own grids' positions: their render at the final weights was kept
        stored = self.corrections.stored_rows(cell_ids, grid_ids)
        if grid_xyz is not None and (stored >= 0).any():
            mine = np.flatnonzero(stored >= 0)
            own = self.scene.grid_positions(np.asarray(grid_ids).reshape(-1)[mine])
            stored[mine[np.abs(xyz[mine] - own).max(1) > 1e-3]] = -1
        # each distinct (cell, position to the mm) once, in the order of the cells and then of first asking
        answered = np.flatnonzero(~skip & (stored < 0))
        key = np.column_stack([cells[answered].astype(np.float64), np.round(xyz[answered], 3) + 0.0])  # no −0.0
        _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
        first_rows = answered[first]
        order = np.lexsort((first_rows, cells[first_rows]))
        todo = first_rows[order]
        slot = np.empty(order.size, np.int64)
        slot[order] = np.arange(order.size)
        out = torch.zeros(len(cells), self.angle_grid.num_bins, device=self.device)
        rendered = torch.zeros(len(todo), self.angle_grid.num_bins, device=self.device)
        for start in range(0, len(todo), PAIR_CHUNK):
            rows = todo[start : start + PAIR_CHUNK]
            c = torch.as_tensor(cells[rows], device=self.device)
            g = torch.as_tensor(xyz[rows], dtype=torch.float32, device=self.device)
            bins, values = R.output(c, g, self.position)
            rendered[start : start + len(rows)].scatter_add_(1, bins, values)
        if todo.size:
            src = torch.as_tensor(slot[inverse.reshape(-1)], dtype=torch.long, device=self.device)
            out[torch.as_tensor(answered, dtype=torch.long, device=self.device)] = rendered[src]
        if (stored >= 0).any():
            kept = self.corrections.rendered
            assert kept is not None
            out = kept.apply(out, cell_ids, grid_ids, owned=True)
        out = self.corrections.apply(out, cells, cell_ids, grid_ids, owned=True).mul_(self.scene.x_ref)
        w = self.corrections.unseen_weight
        anchors = self.corrections.anchors
        if w > 0.0 and anchors is not None and len(anchors):
            grid_ids = np.asarray(grid_ids, np.int64).reshape(-1)
            cell_ids = np.asarray(cell_ids, np.int64).reshape(-1)
            unseen = ~np.isin(grid_ids, anchors.index.get_level_values("grid_id").to_numpy()) & ~skip
            blend = np.flatnonzero(unseen)
            near = self._nearest_anchored(cell_ids[blend], xyz[blend])
            close = self._within_reach(near, xyz[blend])
            blend, near = blend[close], near[close]
            if blend.size:  # the cell's nearest anchored grid has an anchor: no further blend there
                at = torch.as_tensor(blend, dtype=torch.long, device=self.device)
                # each (cell, nearest anchored grid) once: many unseen grids share one (10 to 1 in the field regime)
                pairs, back = np.unique(np.stack([cell_ids[blend], near], 1), axis=0, return_inverse=True)
                nearest = self.aps(pairs[:, 0], pairs[:, 1])[torch.as_tensor(back.reshape(-1), device=self.device)]
                out[at] = (1.0 - w) * out[at] + w * nearest
        return out

    def _within_reach(self, near: np.ndarray, xyz: np.ndarray) -> np.ndarray:
        """bool ``[n]``: the rows whose nearest anchored grid ``near`` (−1: none) lies within ``BLEND_REACH`` times
        the anchored grids' median spacing (each one's distance to the nearest other) of ``xyz [n, 3]``: the blend
        was measured at unseen grids a grid spacing or two from a measured one, not far from every one."""
        assert self.scene is not None
        ok = near >= 0
        anchors = self.corrections.anchors
        if not ok.any() or anchors is None:
            return ok
        grids = np.unique(anchors.index.get_level_values("grid_id").to_numpy(np.int64))
        if grids.size < 2:
            return ok
        from scipy.spatial import cKDTree

        spacing = cKDTree(self.scene.grid_positions(grids)).query(self.scene.grid_positions(grids), k=2)[0][:, 1]
        reach = BLEND_REACH * float(np.median(spacing))
        dist = np.full(len(near), np.inf)
        dist[ok] = np.linalg.norm(self.scene.grid_positions(near[ok]) - xyz[ok], axis=1)
        return ok & (dist <= reach)

    def _nearest_anchored(self, cell_ids: np.ndarray, xyz: np.ndarray, exclude: np.ndarray | None = None) -> np.ndarray:
        """Per row, the grid id of the anchored grid of that cell nearest to ``xyz [n, 3]`` (−1 where the cell has
        none), among the anchored grids not in ``exclude``."""
        assert self.scene is not None
        out = np.full(len(cell_ids), -1, np.int64)
        anchors = self.corrections.anchors
        if anchors is None or not len(anchors):
            return out
        cells = anchors.index.get_level_values("cell_id").to_numpy(np.int64)
        grids = anchors.index.get_level_values("grid_id").to_numpy(np.int64)
        if exclude is not None and len(exclude):
            keep = ~np.isin(grids, exclude)
            cells, grids = cells[keep], grids[keep]
        from scipy.spatial import cKDTree

        for cell in np.unique(cell_ids):
            mine = grids[cells == cell]
            if not mine.size:
                continue
            rows = np.flatnonzero(cell_ids == cell)  # a k-d tree: no [rows, grids] distance matrix at scale
            out[rows] = mine[cKDTree(self.scene.grid_positions(mine)).query(xyz[rows], k=1)[1]]
        return out

    def rsrp_mix(self, cell_ids: np.ndarray, grid_ids: np.ndarray, beam_type: str) -> RsrpMix | None:
        """WNOMP's APS of the posterior pairs' own reports, averaged in dB into their ``beam_type`` predictions with
        each pair's weight (its group's, chosen per beam type on held-aside reports;
        :class:`~rflscm.models.source.RsrpMix`); None where no pair asked has one."""
        mix = self.corrections.mix_for(beam_type)
        if mix is None or mix.weight is None or self.scene is None:
            return None
        rows = mix.rows(cell_ids, grid_ids)
        if not (rows >= 0).any():
            return None
        zeros = torch.zeros(len(rows), self.angle_grid.num_bins, device=self.device)
        cells, grids = np.asarray(cell_ids).reshape(-1), np.asarray(grid_ids).reshape(-1)
        aps = mix.apply(zeros, cells, grids, owned=True).mul_(self.scene.x_ref)
        weight = torch.zeros(len(rows), device=self.device)
        found = torch.as_tensor(np.flatnonzero(rows >= 0), dtype=torch.long, device=self.device)
        weight[found] = mix.weight.to(self.device)[
            torch.as_tensor(rows[rows >= 0], dtype=torch.long, device=self.device)
        ]
        return RsrpMix(aps, weight)

    def round1_caps(self, cell_ids: np.ndarray, grid_ids: np.ndarray) -> np.ndarray | None:
        """Per pair the most [mW] its strongest round-1 SSB beam may be predicted at: round 1's threshold for a pair it
        did not report at a grid it visited (:class:`~rflscm.models.rflscm.corrections.RoundOneCensor`), NaN
        elsewhere; None without a table (rule ``sinr``, or a checkpoint from before it)."""
        censor = self.corrections.censor
        return None if censor is None else censor.caps_mw(cell_ids, grid_ids)

    def level_offset_db(
        self, cell_ids: np.ndarray, beam_type: str, grid_ids: np.ndarray | None = None
    ) -> np.ndarray | None:
        """CSI-RS predictions carry each cell's CSI-RS level correction relative to its SSB one (the APS carries
        the SSB one; :mod:`~rflscm.models.rflscm.corrections`).  A pair answered by WNOMP's APS of its reports has
        none; a pair round 1 did not report at a grid it visited (its level held to round 1's silence, the cap of
        :meth:`round1_caps`) has the median of the cells' corrections: a cell's own, fitted where the field's level
        stands, spread over tens of dB on weakly trained models, while what all cells share (a CSI-RS power offset of
        the network) still applies."""
        if self.scene is None:
            return None
        offset = self.corrections.level_offset_db(self.scene.cell_index(np.asarray(cell_ids)), beam_type)
        if offset is not None and grid_ids is not None:
            offset = np.where(self.corrections.unrendered(cell_ids, grid_ids), 0.0, offset)
            caps = self.round1_caps(cell_ids, grid_ids)
            if caps is not None and np.isfinite(caps).any():
                every = self.corrections.level_offset_db(np.arange(len(self.scene.cell_ids)), beam_type)
                assert every is not None
                offset = np.where(np.isfinite(caps), float(np.median(every)), offset)
        return offset

    def finish_training(
        self,
        progress: bool = False,
        time_left: TimeLeftFn | None = None,
        clock: Callable[[], float] = time.perf_counter,
        render_rest: bool = False,
        extra_left: TimeLeftFn | None = None,
    ) -> None:
        """After the last step: fit the pair corrections that predictions and the checkpoint carry, once (one
        render of every training pair; ``progress``: a bar).  With ``time_left`` (seconds left on ``clock``, a budget
        run's) the pass is sized to the time left, renders the pairs it leaves itself where a caller would render them
        later (``render_rest``), and corrects the pairs beyond its least only within ``extra_left`` where that is
        given (:func:`~rflscm.models.rflscm.corrections.fit_corrections`)."""
        train = self._training()
        assert self.scene is not None
        self.corrections = fit_corrections(
            self.config.corrections,
            train.data,
            train.num_ssb,
            np.asarray(self.scene.cell_ids),
            self._render_training,
            self._training().columns,
            self.config.train.seed,
            progress,
            time_left,
            clock,
            visible=torch.as_tensor(self.scene.visible, device=self.device),
            render_rest=render_rest,
            extra_left=extra_left,
            known=self._pass_times,
        )
        if self._silence_dbm is not None:
            reported = train.data.observed.any(1).cpu().numpy()
            ids = np.asarray(self.scene.cell_ids, np.int64)[train.data.cell_index.cpu().numpy()[reported]]
            grids = np.asarray(train.data.grid_ids, np.int64)[reported]
            self.corrections.censor = RoundOneCensor(
                pd.MultiIndex.from_arrays([ids, grids], names=["cell_id", "grid_id"]),
                np.unique(grids),
                self._silence_dbm,
            )
        cfg = self.config.corrections
        if self._blend_grids.size:
            self._choose_unseen_blend()
        elif cfg.unseen_blend_grids is not None:
            self.corrections.unseen_weight = UNSEEN_WEIGHT
            self.run_info["unseen_blend"] = {"weight": UNSEEN_WEIGHT, "held_out_grids": 0.0, "held_out_pairs": 0.0}
        if cfg.pair_anchors or cfg.pair_posterior:  # per-pair corrections: how many pairs the pass reached
            fallback, mix, kept = self.corrections.fallback, self.corrections.mix, self.corrections.rendered
            post = self.corrections.posterior
            self.run_info["corrections"] = {
                "training_pairs": float(int(train.data.observed.any(1).sum())),
                "corrected_pairs": self.corrections.corrected_pairs(),
                "wnomp_pairs": float(len(fallback.index)) if fallback is not None else 0.0,
                "budget_choice": float(fallback is not None and "budget" in fallback.scores),
                "mixed_pairs": float(len(mix.index)) if mix is not None else 0.0,
                "rendered_pairs": float(len(kept.index) - self.corrections.borrowed) if kept is not None else 0.0,
                "borrowed_pairs": float(self.corrections.borrowed),
                "level_pairs_per_cell": float(self.corrections.level_pairs),
                "anchor_kappa": self.corrections.anchor_kappa,
                "lambda_pairs": float(sum(g["pairs"] for g in post.groups)) if post is not None else 0.0,
            }

    @torch.no_grad()
    def _choose_unseen_blend(self) -> None:
        """The unseen-grid blend's weight, chosen on the reports of the grids held out of the field's training: each
        held-out pair predicted by the field with the cell's level (as an unseen grid is), blended with the model at
        the cell's nearest anchored grid that was trained on (:func:`choose_blend`)."""
        d, train = self._training().data, self._training()
        assert self.scene is not None
        rows = np.flatnonzero(np.isin(d.grid_ids, self._blend_grids) & d.observed.any(1).cpu().numpy())
        cell_index = d.cell_index.cpu().numpy()[rows]
        cell_ids = np.asarray(self.scene.cell_ids, np.int64)[cell_index]
        xyz = d.grid_xyz.cpu().double().numpy()[rows]
        near = self._nearest_anchored(cell_ids, xyz, exclude=self._blend_grids)
        ok = self._within_reach(near, xyz)
        rows, cell_index, cell_ids, near = rows[ok], cell_index[ok], cell_ids[ok], near[ok]
        weight, scores = 0.0, dict[float, float]()
        if rows.size:
            fitted = self.corrections
            offset = fitted.level_offset_db(cell_index, "csi")  # CSI-RS reports carry the cell's CSI-RS level
            own, nearest = [], []
            for start in range(0, rows.size, PAIR_CHUNK):
                part = slice(start, start + PAIR_CHUNK)
                self.corrections = PairCorrections(levels=fitted.levels)  # the held-out grids as unseen: level only
                try:
                    own_aps = self.aps(cell_ids[part], d.grid_ids[rows[part]])
                finally:
                    self.corrections = fitted
                near_aps = self.aps(cell_ids[part], near[part])
                a = train.a_norm[torch.as_tensor(cell_index[part], device=self.device)]
                gain = torch.ones(a.shape[0], a.shape[1], device=self.device)
                if offset is not None:
                    csi = torch.as_tensor(10.0 ** (offset[part] / 10.0), dtype=gain.dtype, device=self.device)
                    gain[:, train.num_ssb :] = csi[:, None]
                x_ref = self.scene.x_ref
                own.append(torch.einsum("bmn,bn->bm", a, own_aps / x_ref) * gain)
                nearest.append(torch.einsum("bmn,bn->bm", a, near_aps / x_ref) * gain)
            at = torch.as_tensor(rows, device=self.device)
            weight, scores = choose_blend(torch.cat(own), torch.cat(nearest), d.rsrp[at], d.observed[at])
        self.corrections.unseen_weight = weight
        self.run_info["unseen_blend"] = {
            "weight": weight,
            "held_out_grids": float(self._blend_grids.size),
            "held_out_pairs": float(rows.size),
            "mae_db": {str(w): round(v, 4) for w, v in scores.items()},
        }

    def finish_seconds(
        self, clock: Callable[[], float] = time.perf_counter, fresh: FreshPairs | None = None
    ) -> PassCost:
        """What :meth:`finish_training` would cost for every training pair, in seconds of ``clock``, measured now on
        two chunks of the pass at the final schedule position (the refinement model's render), what one more
        render costs per pair (an evaluation's), and, given a caller's ``fresh`` pairs (without training reports),
        what theirs cost (:meth:`_fresh_render_s`)."""
        train = self._training()
        assert self.scene is not None
        final = float(self.config.train.steps)
        times = measure_pass(
            self.config.corrections,
            train.data,
            train.num_ssb,
            len(self.scene.cell_ids),
            lambda pairs: self._render_training(pairs, final),
            train.columns,
            clock,
            torch.as_tensor(self.scene.visible, device=self.device),
        )
        self._pass_times = times
        pairs = int(train.data.observed.any(1).sum())
        cfg, cells = self.config.corrections, len(self.scene.cell_ids)
        fresh_s = None if fresh is None else self._fresh_render_s(fresh, final, clock)
        return PassCost(times.total_s(cfg, pairs), times.render_s, times.least_s(cfg, pairs, cells), fresh_s)

    @torch.no_grad()
    def _fresh_render_s(self, fresh: FreshPairs, position: float, clock: Callable[[], float]) -> float | None:
        """Seconds per pair [s of ``clock``] of rendering ``fresh`` pairs at schedule ``position`` as the caller's
        :meth:`aps` calls will (:attr:`FreshPairs.calls`: each call's pairs sorted by cell, ``PAIR_CHUNK`` at a time,
        so a call of a few pairs pays a chunk's set-up alone); None when no pair's cell is the model's (the caller's
        renders then fail, costing nothing).

        Chunks evenly spaced over the calls' order are timed one by one, about ``FRESH_PAIRS`` pairs of them (at
        least two chunks, at most ``FRESH_CHUNKS``), and every chunk is priced as ``set-up + pairs × rate``, both
        fitted to those times by least squares (where the timed chunks differ in size; else their mean time each)."""
        assert self.scene is not None
        known = np.isin(np.asarray(fresh.cell_ids, np.int64), self.scene.cell_ids)
        if not known.any():
            return None
        cells = self.scene.cell_index(np.asarray(fresh.cell_ids, np.int64)[known])
        xyz = np.asarray(fresh.grid_xyz, np.float64).reshape(-1, 3)[known]
        calls = np.zeros(cells.size, np.int64) if fresh.calls is None else np.asarray(fresh.calls, np.int64)[known]
        order = np.lexsort((cells, calls))
        bounds = np.flatnonzero(np.diff(calls[order])) + 1
        chunks = [part[a : a + PAIR_CHUNK] for part in np.split(order, bounds) for a in range(0, part.size, PAIR_CHUNK)]
        count = int(np.clip(round(FRESH_PAIRS * len(chunks) / cells.size), 2, FRESH_CHUNKS))
        picked = np.unique(np.linspace(0, len(chunks) - 1, count).round().astype(np.int64))
        R = self._renderer()
        sizes, times = np.array([chunks[i].size for i in picked], np.float64), np.zeros(picked.size)
        for j, i in enumerate(picked):
            begun = clock()
            c = torch.as_tensor(cells[chunks[i]], device=self.device)
            R.output(c, torch.as_tensor(xyz[chunks[i]], dtype=torch.float32, device=self.device), position)
            if self.device.type == "cuda":  # each chunk's own time, not its kernels' launch
                torch.cuda.synchronize(self.device)
            times[j] = clock() - begun
        setup, rate = float(times.mean()), 0.0
        if np.ptp(sizes) > 0:
            setup, rate = np.linalg.lstsq(np.column_stack([np.ones_like(sizes), sizes]), times, rcond=None)[0]
            if setup < 0.0:
                setup, rate = 0.0, float(times.sum() / sizes.sum())
            elif rate < 0.0:
                setup, rate = float(times.mean()), 0.0
        return (setup * len(chunks) + rate * cells.size) / cells.size

    @torch.no_grad()
    def _render_training(
        self, pairs: torch.Tensor, position: float | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The APS of training ``pairs [B]`` at schedule ``position`` (default: the latest step's) in sparse form
        ``(fine bins [B, K], values [B, K])`` and their predicted round-1 reports ``[B, M]`` (normalised); during
        HiTAM's warm-up through the coarse columns, which give the same A x as the coarse APS spread over its blocks,
        on ~β² fewer columns."""
        d, R = self._training().data, self._renderer()
        position = self.position if position is None else position
        cells, xyz = d.cell_index[pairs], d.grid_xyz[pairs]
        a_coarse = self._training().a_coarse
        if self.hitam is not None and a_coarse is not None and position < self.hitam.warmup_steps:
            coarse = R.coarse_power(cells, xyz)
            bins, values = R.coarse_as_fine(coarse)
            return bins, values, torch.einsum("bmk,bk->bm", a_coarse[cells], coarse)
        bins, values = R.output(cells, xyz, position)
        return bins, values, torch.einsum("bmk,bk->bm", self._training().columns(cells, bins), values)

    # --- persistence (:mod:`~rflscm.models.rflscm.checkpoint`) ---------------------------------------
    def state_dict_for_checkpoint(self) -> dict[str, Any]:
        return checkpoint.model_state(self)

    @classmethod
    def from_checkpoint(cls, state: dict[str, Any], device: torch.device | str = "cpu") -> RFLSCM:
        return checkpoint.restore(cls, state, device)

    def _load_stage_weights(self, weights: dict[str, torch.Tensor]) -> None:
        checkpoint.load_stage_weights(self, weights)
        if self._train is not None:
            self._train.selection = None
