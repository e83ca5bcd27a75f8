"""RF-LSCM: the radiance-field localized statistical channel model (paper §III–IV, SPEC §3).

``RFLSCM`` implements the model contract (:mod:`rflscm.models.base`).  It owns HiTAM, the
training data and the losses; it composes an :class:`~rflscm.models.rflscm.renderer.APSRenderer`
(rays, visibility, HiTAM's selection; no parameters) over its rendering stages
(:class:`~rflscm.models.rflscm.fields.RadianceStage`: fields and decoder).  The fields come from the
:class:`~rflscm.models.rflscm.fields.FieldFactory` given at construction — the one seam through which
NeRF²-LSCM plugs in MLP fields instead of VM tensors and reuses everything else.

Units: the stages render the APS in the normalised unit x_ref = r_ref / a_ref (see
:mod:`rflscm.models.pairs`); :meth:`aps` returns linear path gain.  Training is driven from above by
the trainer's ``fit`` (package ``train``) through the the trainer's ``Trainable`` protocol methods (``prepare``, ``training_losses``, …).

Decisions where the paper is silent (the constants and options of :mod:`~rflscm.models.rflscm.config`):

* media: 3 passive degrees of freedom (loss on a log scale at a reference carrier, excess real
  index, real μ ≥ 1), each on its own VM factors; FDAM itself is exact, δ^Φ uses the continuous
  branch of log δ; the cumulative |Π δ̃| is capped at 1 (a passivity guard: single FDAM factors
  can exceed 1);
* empty-space skipping from Φ is exact (Φ = 0 samples are inert); a ray's fields are computed
  once per cell and shared by every grid that looks along it; directions a cell's round-1 beams
  cannot see (−30 dB) are not rendered for that cell;
* decoder: the paper's inputs plus the sample-to-grid geometry (direction, half-vector, log
  distances, distance relative to the ray's cone), polar output (log |R|, arg R) with free-space
  and bistatic spreading factors, level calibrated to the data at initialisation;
* attenuation initialised from the classified scan (walls opaque, ground and air transparent);
* HiTAM: coarse rays through block centres with block-mean columns; the refinement model starts
  as a copy of the coarse one, rescaled to the coarse model's level;
* loss in bels by default (paper: linear), L1 relative to each pair's power scale;
* after training, predictions carry a level correction per cell and beam type, a level anchor per
  training pair (the median error left on the pair's own round-1 reports) and a posterior per training
  pair (per-bin gains fitted to those reports under a ridge prior centred on the field,
  :mod:`~rflscm.models.rflscm.posterior`); the paper predicts from the field alone (docs/DECISIONS.md,
  "Learning faster").
"""

from __future__ import annotations

import dataclasses
import math
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, cast

import numpy as np
import pandas as pd
import torch
from torch import nn

from rflscm.config import from_dict, to_dict
from rflscm.data import BEAM_TYPES
from rflscm.errors import CheckpointError
from rflscm.fields import PassiveMedium, TensorVM
from rflscm.fields.point_prior import PointPrior
from rflscm.fields.surfaces import SurfaceOrientation
from rflscm.geometry import AngleGrid
from rflscm.models.base import LSCMModel, TrainingPlan, register_model
from rflscm.models.pairs import PairData, build_pair_data, reference_power, stacked_sensing
from rflscm.models.rflscm.config import (
    ANY,
    FLOOR_DB,
    INIT_LEVEL_DB,
    INIT_LOSS_DB,
    LEARN_MU,
    VAL_BEAM_FRACTION,
    RFLSCMConfig,
    TrainConfig,
    load_rflscm_config,
)
from rflscm.models.rflscm.fields import (
    FieldFactory,
    RadianceDecoder,
    RadianceStage,
    SceneFields,
    SceneFrame,
    VMFieldFactory,
)
from rflscm.models.rflscm.hitam import HiTAM
from rflscm.models.rflscm.losses import lscm_loss, mae_db
from rflscm.models.rflscm.posterior import (
    HOLDOUT,
    LAMBDA_PAIRS,
    POSTERIOR_BINS,
    LambdaChoice,
    PairPosterior,
    fit_gains,
)
from rflscm.models.rflscm.renderer import APSRenderer
from rflscm.models.rflscm.scene import (
    SceneInfo,
    building_targets,
    check_scene_box,
    make_frame,
    make_prior,
    make_surfaces,
    prior_from_state,
    prior_state,
    scene_box,
    surfaces_from_state,
    surfaces_state,
    visible_bins,
)

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario

PAIR_CHUNK = 64  # pairs per inference chunk (A columns and APS rows stay small)
LEVEL_PAIRS_PER_CELL = 16
"""Training pairs per cell (evenly spaced) on which the level correction is measured."""
LEVEL_MIN_BEAMS = 10
"""A cell's own median needs this many reported beams of a type; fewer: the median over every cell."""


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

    def __init__(self, config: RFLSCMConfig, angle_grid: AngleGrid, device: torch.device | str = "cpu",
                 fields: FieldFactory | None = None) -> None:  # fmt: skip
        """``fields`` builds each stage's fields (default: RF-LSCM's VM tensors from ``config.field``)."""
        super().__init__(angle_grid, device)
        self.config = config
        self.fields: FieldFactory = fields if fields is not None else VMFieldFactory(config.field)
        h = config.hitam
        self.hitam = HiTAM(angle_grid, h.beta, h.top_k, "block", h.warmup_steps, h.ramp_steps) if h.enabled else None
        self.scene: SceneInfo | None = None
        self.prior: PointPrior | None = None
        self.surfaces: SurfaceOrientation | None = None
        """The scan's surface orientation (decoder's specular cue), or None."""
        self.stages = nn.ModuleDict()
        self.step = 0
        """Training steps done."""
        self.position = -1.0
        """Schedule position of the latest training step begun (units of ``train.steps``, see the trainer's
        ``Trainable``; −1 before the first).  In step mode ``step − 1``; HiTAM and upsampling follow it."""
        self.train_state: dict[str, Any] | None = None
        self.renderer: APSRenderer | None = None
        """Built with the stages (fit or checkpoint)."""
        self.levels: torch.Tensor | None = None
        """``[C, 2]`` level correction [dB] of each cell's SSB (column 0) and CSI-RS (1) predictions
        (``train.calibrate_levels``; see :meth:`_fit_levels`), or None."""
        self._levels_step: int | None = None
        self.anchors: pd.Series | None = None
        """Per-pair level anchor [dB] indexed by (cell_id, grid_id) (``train.pair_anchors``; see
        :meth:`_fit_pair_corrections`), or None."""
        self.posterior: PairPosterior | None = None
        """The training pairs' posterior gains (``train.pair_posterior``), or None."""
        self._pairs_step: int | None = None
        self._train: _TrainContext | None = None

    @classmethod
    def build(cls, config: str | Path | dict[str, Any] | None = None, angle_grid: AngleGrid | None = None,
              device: torch.device | str = "cpu") -> RFLSCM:  # fmt: skip
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
            cell_ids, cell_xyz, wavelengths, grids["grid_id"].to_numpy(np.int64), grids[["x", "y", "z"]].to_numpy(np.float64),
            r_ref, a_ref, make_frame(cfg, lo, hi, cell_xyz, wavelengths, dist), visible_bins(a_mw, cfg.render.min_gain_db),
        )  # fmt: skip
        prior = make_prior(cfg, scenario, lo, hi)
        self.prior = prior.to(self.device) if prior is not None else None
        surfaces = make_surfaces(cfg, scenario, lo, hi, seed=cfg.train.seed)
        self.surfaces = surfaces.to(self.device) if surfaces is not None else None
        self._build_stages(self.scene.frame)
        targets = building_targets(cfg, scenario, prior, seed=cfg.train.seed) if prior is not None else None
        if targets is not None:
            self._init_attenuation(*targets)
        a_coarse = self.hitam.coarse_columns(a_norm) if self.hitam is not None else None
        self._train = _TrainContext(data.to(self.device), a_norm, a_coarse, num_ssb)
        self.levels, self._levels_step = None, None
        self.anchors, self.posterior, self._pairs_step = None, None, None
        self.step, self.position, self.train_state = 0, -1.0, None
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
        pairs = torch.nonzero(d.beam_mask.any(1)).squeeze(1).cpu()
        return TrainingPlan(pairs, d.cell_index.cpu()[pairs])

    def resume_from(self, payload: dict[str, Any], path: str | Path) -> dict[str, Any]:
        """Load weights and step from the checkpoint ``payload`` of ``path`` (it must hold this model of this
        scenario with the same config); returns the trainer state saved with it."""
        state = payload["state"]
        if payload["model"] != self.name:
            raise CheckpointError(
                f"{path}: cannot resume: it holds a {payload['model']!r} model, not {self.name!r}; train {self.name} "
                "into another file, or without --resume to overwrite it."
            )
        if payload["fingerprint"] != self.fingerprint:
            raise CheckpointError(f"{path}: cannot resume: it was trained on another scenario (or other data).")
        try:
            theirs = _without_removed_options(state["config"], self.config_class)
        except CheckpointError as exc:
            raise CheckpointError(f"{path}: cannot resume: {exc}") from None
        ours = to_dict(self.config)
        steps_now, steps_then = ours["train"]["steps"], dict(theirs.get("train") or {}).get("steps")
        if steps_now != steps_then:
            raise CheckpointError(
                f"{path}: cannot resume: it was trained towards `train.steps` = {steps_then}, this run asks for "
                f"{steps_now}; the learning-rate schedule (lr_decay ** (step / steps)) depends on it. Resume with "
                f"`train.steps: {steps_then}`, or train afresh without --resume."
            )
        if ours != theirs:
            keys = _changed_keys(ours, theirs)
            raise CheckpointError(
                f"{path}: cannot resume: the checkpoint was trained with another config (changed: "
                f"{', '.join(keys[:5]) or 'layout'}); resume with its config or train afresh without --resume."
            )
        if state.get("train_state") is None:
            raise CheckpointError(f"{path}: cannot resume: the checkpoint holds no optimizer state.")
        self._load_stage_weights(state["stages"])
        self.step, self.position = _step_and_position(state)
        return state["train_state"]

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
        before, self.step, self.position = self.position, step, position
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

    def _training(self) -> _TrainContext:
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
            pred, d.rsrp[pairs], d.beam_mask[pairs], x, d.x_scale[pairs], d.bound[pairs],
            c.fidelity, c.sparsity, c.missing_penalty, floor=10.0 ** (FLOOR_DB / 10.0),
        )  # fmt: skip

    def _columns(self, cells: torch.Tensor, bins: torch.Tensor, valid: torch.Tensor | None = None) -> torch.Tensor:
        """Normalised A columns ``[B, M, K]`` of fine ``bins [B, K]`` (zeroed where not ``valid``)."""
        a = self._training().a_norm
        beams = torch.arange(a.shape[1], device=a.device)
        cols = a[cells[:, None, None], beams[None, :, None], bins[:, None, :]]
        return cols if valid is None else cols * valid[:, None, :].to(cols.dtype)

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
                self._columns(cells, bins, valid), self._renderer().fine_power(cells, xyz, bins, valid), pairs
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
            memo = (torch.zeros(d.num_pairs, width, dtype=torch.long, device=self.device),
                    torch.zeros(d.num_pairs, width, dtype=torch.bool, device=self.device),
                    torch.zeros(d.num_pairs, dtype=torch.bool, device=self.device))  # fmt: skip
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
    def _median_error_db(self, stage: str, num_pairs: int = 64) -> float:
        """Median (prediction − measurement) [dB] of ``stage``'s APS over the observed beams of a few training pairs."""
        d = self._training().data
        pairs = torch.arange(d.num_pairs, device=self.device)[:: max(1, d.num_pairs // num_pairs)][:num_pairs]
        cells, xyz = d.cell_index[pairs], d.grid_xyz[pairs]
        if self.hitam is None:
            bins, values = self._renderer().output(cells, xyz, self.position)
        elif stage == "coarse":
            bins, values = self._renderer().coarse_as_fine(self._renderer().coarse_power(cells, xyz))
        else:
            bins, valid = self._renderer().expand(cells, self._renderer().coarse_power(cells, xyz))
            values = self._renderer().fine_power(cells, xyz, bins, valid)
        pred = torch.einsum("bmk,bk->bm", self._columns(cells, bins), values)
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

        Each distinct (cell, grid position) of the call is rendered once; evaluation and the benchmarks
        remember rendered APS across calls (:class:`rflscm.eval.cache.APSCache`)."""
        if self.scene is None or self.renderer is None:
            raise RuntimeError("the model has not been fitted")
        R = self.renderer
        cells = self.scene.cell_index(cell_ids)
        xyz = (
            self.scene.grid_positions(grid_ids) if grid_xyz is None else np.asarray(grid_xyz, np.float64).reshape(-1, 3)
        )
        keys = [(int(c), *np.round(p, 3).tolist()) for c, p in zip(cells, xyz)]
        first: dict[tuple, int] = {}
        for i, key in enumerate(keys):
            first.setdefault(key, i)
        todo = sorted(first.values(), key=lambda i: (keys[i][0], i))
        out = torch.zeros(len(keys), self.angle_grid.num_bins, device=self.device)
        rendered = torch.zeros(len(todo), self.angle_grid.num_bins, device=self.device)
        for start in range(0, len(todo), PAIR_CHUNK):
            rows = todo[start : start + PAIR_CHUNK]
            c = torch.as_tensor(cells[rows], device=self.device)
            g = torch.as_tensor(xyz[rows], dtype=torch.float32, device=self.device)
            bins, values = R.output(c, g, self.position)
            rendered[start : start + len(rows)].scatter_add_(1, bins, values)
        if keys:
            slot = {keys[i]: j for j, i in enumerate(todo)}
            out = rendered[torch.as_tensor([slot[k] for k in keys], dtype=torch.long, device=self.device)]
        levels = self.current_levels()
        if levels is not None:
            out = out * torch.pow(10.0, levels[torch.as_tensor(cells, device=self.device), 0] / 10.0)[:, None]
        anchors = self.current_anchors()
        if anchors is not None and len(anchors) and len(keys):
            at = pd.MultiIndex.from_arrays(
                [np.asarray(cell_ids, np.int64).reshape(-1), np.asarray(grid_ids, np.int64).reshape(-1)]
            )
            shift = torch.as_tensor(
                anchors.reindex(at).fillna(0.0).to_numpy(np.float32, copy=True), dtype=torch.float32, device=self.device
            )
            out = out * torch.pow(10.0, shift / 10.0)[:, None]
        posterior = self.current_posterior()
        if posterior is not None:
            out = posterior.apply(
                out, np.asarray(cell_ids, np.int64).reshape(-1), np.asarray(grid_ids, np.int64).reshape(-1)
            )
        return out * self.scene.x_ref

    def level_offset_db(self, cell_ids: np.ndarray, beam_type: str) -> np.ndarray | None:
        """CSI-RS predictions carry each cell's CSI-RS level correction relative to its SSB one (the APS carries
        the SSB correction); see :meth:`current_levels`."""
        levels = self.current_levels()
        if levels is None or beam_type != "csi" or self.scene is None:
            return None
        relative = (levels[:, 1] - levels[:, 0]).cpu().double().numpy()
        return relative[self.scene.cell_index(np.asarray(cell_ids))]

    # --- level correction -------------------------------------------------------------------------
    def current_levels(self) -> torch.Tensor | None:
        """The level correction ``[C, 2]`` [dB] for the current weights (re-measured when the weights moved
        since it was last measured on the training data), or None when switched off or not known."""
        if not self.config.train.calibrate_levels:
            return None
        if self._train is not None and self._levels_step != self.step:
            self.levels, self._levels_step = self._fit_levels(), self.step
        return self.levels

    def current_anchors(self) -> pd.Series | None:
        """The per-pair level anchors [dB] for the current weights (re-measured, like :meth:`current_levels`, when
        the weights moved since the last measurement), or None when switched off or not known."""
        if not self.config.train.pair_anchors:
            return None
        self._refresh_pair_corrections()
        return self.anchors

    def current_posterior(self) -> PairPosterior | None:
        """The training pairs' posterior gains (``train.pair_posterior``, :mod:`~rflscm.models.rflscm.posterior`) for the
        current weights, re-measured like :meth:`current_anchors`, or None when switched off or not known."""
        if not self.config.train.pair_posterior:
            return None
        self._refresh_pair_corrections()
        return self.posterior

    def _refresh_pair_corrections(self, progress: bool = False) -> None:
        if self._train is not None and self._pairs_step != self.step:
            self.anchors, self.posterior = self._fit_pair_corrections(progress)
            self._pairs_step = self.step

    def finish_training(self, progress: bool = False) -> None:
        """After the last step: measure the level correction, the pair anchors and the pair posterior that
        predictions and the checkpoint carry (one render of every training pair; ``progress``: a bar)."""
        if self.config.train.pair_anchors or self.config.train.pair_posterior:
            self._refresh_pair_corrections(progress)  # measures the level correction on the same render
        self.current_levels()

    def _level_picks(self) -> torch.Tensor:
        """The training pairs the level correction is measured on: up to ``LEVEL_PAIRS_PER_CELL`` evenly spaced
        pairs with reports per cell (sorted)."""
        d = self._training().data
        assert self.scene is not None
        reported = d.observed.any(1)
        picks = []
        for c in range(len(self.scene.cell_ids)):
            p = torch.nonzero(reported & (d.cell_index == c)).squeeze(1)
            if p.numel():
                picks.append(p[torch.linspace(0, p.numel() - 1, min(p.numel(), LEVEL_PAIRS_PER_CELL)).round().long()])
        return torch.cat(picks).unique() if picks else torch.zeros(0, dtype=torch.long, device=self.device)

    @torch.no_grad()
    def _fit_levels(self, rendered: _Rendered | None = None) -> torch.Tensor:
        """Median (measured − predicted) [dB] over the reported round-1 training beams of the
        :meth:`_level_picks`, per cell and beam type (the median over every cell where a cell has fewer than
        ``LEVEL_MIN_BEAMS`` such beams; 0 where a type has none); from ``rendered`` when it holds them.

        The training loss weighs each report's reported beams against the bounds of its unreported ones
        (the missing-beam penalty); under top-N or SINR reporting a model that cannot yet resolve the beams
        keeps every beam low to respect the bounds, so its reported beams come out too weak (a CSI-RS bias
        of −3 to −5 dB after a few hundred steps on the shipped scenario).  This correction, measured on the
        reported beams alone, removes that level error from the predictions without touching the field."""
        train = self._training()
        d = train.data
        assert self.scene is not None
        num_cells = len(self.scene.cell_ids)
        levels = torch.zeros(num_cells, 2)
        picks = self._level_picks()
        if not picks.numel():
            return levels.to(self.device)
        if rendered is None:
            rendered = self._render_pairs(picks, top=False)
        pred = rendered.pred[rendered.rows_of(picks)]
        resid = 10.0 * torch.log10(d.rsrp[picks] / pred.clamp_min(1e-30))
        rows, beams = d.observed[picks].nonzero(as_tuple=True)
        r = resid[rows, beams].cpu().double().numpy()
        c = d.cell_index[picks][rows].cpu().numpy()
        t = (beams >= train.num_ssb).cpu().numpy()
        for beam_type in (0, 1):
            of_type = t == beam_type
            if not bool(of_type.any()):
                continue
            levels[:, beam_type] = float(np.median(r[of_type]))  # numpy: no size limit, mean of the middle pair
            for cell in range(num_cells):
                mine = of_type & (c == cell)
                if int(mine.sum()) >= LEVEL_MIN_BEAMS:
                    levels[cell, beam_type] = float(np.median(r[mine]))
        return levels.to(self.device)

    @torch.no_grad()
    def _fit_pair_corrections(self, progress: bool = False) -> tuple[pd.Series | None, PairPosterior | None]:
        """One render of every training pair with reports, then their level anchors and their posterior (and,
        when stale, the level correction, from the same render).

        *Anchor* (``train.pair_anchors``): the median (measured − predicted) [dB] over the pair's reported round-1
        training beams (SSB and CSI-RS pooled, after the level correction).  An under-trained field gets the
        angular shape and the antenna's effect right long before it gets each grid's level (its path loss)
        right; the pair's own reports pin that level, as a per-grid fit would, and a changed antenna moves
        both rounds' paths alike.

        *Posterior* (``train.pair_posterior``): per-bin gains on the anchored APS that fit the same reports
        under a ridge prior centred on the field, λ chosen on held-aside reports
        (:mod:`~rflscm.models.rflscm.posterior`).

        Validation beams are used by neither, so :meth:`validation_mae` stays an honest held-aside score of the
        field alone."""
        from tqdm.auto import tqdm

        cfg = self.config.train
        d = self._training().data
        assert self.scene is not None
        pairs = torch.nonzero(d.observed.any(1)).squeeze(1)
        bar = tqdm(
            total=pairs.numel() * (2 if cfg.pair_posterior else 1), desc="pair corrections", unit="pair",
            disable=not progress, leave=False,
        )  # fmt: skip
        rendered = self._render_pairs(pairs, top=cfg.pair_posterior, bar=bar)
        if cfg.calibrate_levels and self._levels_step != self.step:
            self.levels, self._levels_step = self._fit_levels(rendered), self.step
        lam, scores = math.inf, {}
        if cfg.pair_posterior and pairs.numel():
            # λ from held-aside reports of a spread subset of the pairs, then one fit per pair
            held = torch.rand(d.rsrp.shape, generator=torch.Generator().manual_seed(cfg.seed)) < HOLDOUT
            subset = pairs[torch.linspace(0, pairs.numel() - 1, min(pairs.numel(), LAMBDA_PAIRS)).round().long()]
            choice = LambdaChoice()
            for chunk in self._pair_chunks(rendered, rendered.rows_of(subset.unique())):
                held_here = held[chunk.pairs.cpu()].to(self.device)
                choice.add(*chunk.fit_inputs(), chunk.resid, chunk.mask, held_here)
            lam, scores = choice.best(), choice.mae_db()
        anchors, gains, bins_of = [], [], []
        fitting = cfg.pair_posterior and math.isfinite(lam)
        for chunk in self._pair_chunks(rendered, torch.arange(pairs.numel(), device=self.device), fitting):
            anchors.append(chunk.anchor)
            if chunk.top_bins is not None:
                gains.append(fit_gains(*chunk.fit_inputs(), chunk.resid, chunk.mask, lam).cpu())
                bins_of.append(chunk.top_bins.cpu())
            bar.update(chunk.pairs.numel() if cfg.pair_posterior else 0)
        bar.close()
        cell_ids = np.asarray(self.scene.cell_ids, np.int64)[d.cell_index.cpu().numpy()[pairs.cpu().numpy()]]
        index = pd.MultiIndex.from_arrays([cell_ids, d.grid_ids[pairs.cpu().numpy()]], names=["cell_id", "grid_id"])
        median = torch.cat(anchors).cpu().double().numpy() if anchors else np.zeros(0)
        anchor_series = pd.Series(median, index=index, name="anchor_db") if cfg.pair_anchors else None
        if not cfg.pair_posterior:
            return anchor_series, None
        if not gains:  # no choice of λ beat the field on held-aside reports: nothing to apply
            empty = pd.MultiIndex.from_arrays([np.zeros(0, np.int64)] * 2, names=["cell_id", "grid_id"])
            return anchor_series, PairPosterior(
                empty, torch.zeros(0, 0, dtype=torch.long), torch.zeros(0, 0), lam, scores
            )
        gain_db = torch.cat(gains).half().float()  # as a checkpoint stores it: a loaded model predicts the same
        return anchor_series, PairPosterior(index, torch.cat(bins_of), gain_db, lam, scores)

    @torch.no_grad()
    def _render_pairs(self, pairs: torch.Tensor, top: bool, bar: Any = None) -> _Rendered:
        """Render training ``pairs [P]`` (sorted) ``PAIR_CHUNK`` at a time: their predicted round-1 reports and,
        with ``top``, their ``POSTERIOR_BINS`` strongest bins and the APS there (``bar``: a progress bar)."""
        preds, tops, xs = [], [], []
        for start in range(0, pairs.numel(), PAIR_CHUNK):
            bins, values, pred = self._render_training(pairs[start : start + PAIR_CHUNK])
            preds.append(pred)
            if top:
                best = torch.topk(values, min(POSTERIOR_BINS, values.shape[1]), dim=1).indices
                tops.append(bins.gather(1, best).to(torch.int32))  # kept for every pair: half the memory
                xs.append(values.gather(1, best))
            if bar is not None:
                bar.update(min(PAIR_CHUNK, pairs.numel() - start))
        num_beams = self._training().data.rsrp.shape[1]
        pred = torch.cat(preds) if preds else torch.zeros(0, num_beams, device=self.device)
        return _Rendered(pairs, pred, torch.cat(tops) if tops else None, torch.cat(xs) if xs else None)

    def _pair_chunks(
        self, rendered: _Rendered, rows: torch.Tensor, with_columns: bool = True
    ) -> typing.Iterator[_PairChunk]:
        """Rows ``rows`` of ``rendered``, ``PAIR_CHUNK`` at a time, as the pair corrections see them: each pair's
        anchor and, after level correction and anchor, its residuals and (``with_columns``) its strongest bins
        with their columns."""
        cfg = self.config.train
        train = self._training()
        d = train.data
        observed = d.observed
        levels = self.current_levels()
        beam_type = (torch.arange(d.rsrp.shape[1], device=self.device) >= train.num_ssb).long()
        for start in range(0, rows.numel(), PAIR_CHUNK):
            at = rows[start : start + PAIR_CHUNK]
            batch = rendered.pairs[at]
            cells, pred = d.cell_index[batch], rendered.pred[at]
            resid = 10.0 * torch.log10(d.rsrp[batch] / pred.clamp_min(1e-30))
            if levels is not None:
                resid = resid - levels[cells][:, beam_type]
            mask = observed[batch]
            median = np.nanmedian(torch.where(mask, resid, torch.nan).cpu().double().numpy(), axis=1)
            anchor = torch.as_tensor(median, dtype=resid.dtype, device=resid.device)
            if cfg.pair_anchors:
                resid = resid - anchor[:, None]
            chunk = _PairChunk(batch, anchor, resid, mask)
            if with_columns:
                assert rendered.top_bins is not None and rendered.top_x is not None
                chunk.top_bins, chunk.top_x = rendered.top_bins[at].long(), rendered.top_x[at]
                chunk.cols = self._columns(cells, chunk.top_bins)
                chunk.rest = (pred - torch.einsum("bmk,bk->bm", chunk.cols, chunk.top_x)).clamp_min(0.0)
            yield chunk

    @torch.no_grad()
    def _render_training(self, pairs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The current APS of training ``pairs [B]`` in sparse form ``(fine bins [B, K], values [B, K])`` and their
        predicted round-1 reports ``[B, M]`` (normalised); during HiTAM's warm-up through the coarse columns, which
        give the same A x as the coarse APS spread over its blocks, on ~β² fewer columns."""
        d, R = self._training().data, self._renderer()
        cells, xyz = d.cell_index[pairs], d.grid_xyz[pairs]
        a_coarse = self._training().a_coarse
        if self.hitam is not None and a_coarse is not None and self.position < self.hitam.warmup_steps:
            coarse = R.coarse_power(cells, xyz)
            bins, values = R.coarse_as_fine(coarse)
            return bins, values, torch.einsum("bmk,bk->bm", a_coarse[cells], coarse)
        bins, values = R.output(cells, xyz, self.position)
        return bins, values, torch.einsum("bmk,bk->bm", self._columns(cells, bins), values)

    # --- persistence --------------------------------------------------------------------------
    def state_dict_for_checkpoint(self) -> dict[str, Any]:
        return {
            "config": to_dict(self.config),
            "angle_grid": self.angle_grid.to_dict(),
            "scene": self.scene.to_dict() if self.scene is not None else None,
            "prior": prior_state(self.prior),
            "surfaces": surfaces_state(self.surfaces),
            "stages": {k: v.detach().cpu().clone() for k, v in self.stages.state_dict().items()},
            "step": self.step,
            "position": self.position,
            "levels": self.levels.detach().cpu().clone() if self.levels is not None else None,
            "anchors": _anchors_state(self.anchors),
            "posterior": self.posterior.to_state() if self.posterior is not None else None,
            "train_state": self.train_state,
        }

    @classmethod
    def from_checkpoint(cls, state: dict[str, Any], device: torch.device | str = "cpu") -> RFLSCM:
        config: Any = from_dict(cls.config_class, _without_removed_options(state["config"], cls.config_class))
        model = cls(config, AngleGrid.from_dict(state["angle_grid"]), device)
        if state["scene"] is None:
            raise CheckpointError("this checkpoint holds an unfitted model.")
        model.scene = SceneInfo.from_dict(state["scene"])
        prior = prior_from_state(state["prior"])
        model.prior = prior.to(model.device) if prior is not None else None
        surfaces = surfaces_from_state(state.get("surfaces"))
        model.surfaces = surfaces.to(model.device) if surfaces is not None else None
        model._build_stages(model.scene.frame)
        model._load_stage_weights(state["stages"])
        (model.step, model.position), model.train_state = _step_and_position(state), state.get("train_state")
        levels = state.get("levels")  # none in checkpoints before the level correction: no correction
        model.levels = torch.as_tensor(levels, dtype=torch.float32, device=model.device) if levels is not None else None
        model.anchors = _anchors_from_state(state.get("anchors"))  # none before the pair anchors: none applied
        model.posterior = PairPosterior.from_state(state.get("posterior"), model.angle_grid.num_bins)
        return model

    def _load_stage_weights(self, weights: dict[str, torch.Tensor]) -> None:
        weights = {_current_key(k): v for k, v in weights.items()}
        for name, module in self.stages.named_modules():
            if isinstance(module, TensorVM):
                nx, ny, nz = (int(weights[f"{name}.lines.{a}"].shape[2]) for a in range(3))
                res = (nx, ny, nz)
                if res != module.resolution:
                    module.upsample(res)
        try:
            self.stages.load_state_dict(weights)
        except (RuntimeError, KeyError) as exc:  # a checkpoint of an older layout of the model
            first = str(exc).strip().splitlines()[-1].strip()
            raise CheckpointError(
                f"the checkpoint's weights do not fit this version of {self.name!r} ({first}); retrain it with this version."
            ) from None
        self.stages.to(self.device)
        if self._train is not None:
            self._train.selection = None


def fit_loss_channel(
    fields: SceneFields, points: torch.Tensor, target: torch.Tensor, keep: torch.Tensor, steps: int, lr: float
) -> None:
    """Adam on ``fields``' δ module so that its raw loss channel at ``points [n, 3]`` approaches ``target [n]``
    while its other channels stay at ``keep [n, C_δ − 1]`` (mean squared errors, ``steps`` steps at ``lr``)."""
    opt = torch.optim.Adam(fields.delta_module().parameters(), lr=lr)
    for _ in range(steps):
        out = fields.delta(fields.encode(points))
        loss = (out[:, 0] - target).square().mean() + (out[:, 1:] - keep).square().mean()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()


def _anchors_state(anchors: pd.Series | None) -> dict[str, torch.Tensor] | None:
    if anchors is None:
        return None
    cells, grids = (
        torch.as_tensor(anchors.index.get_level_values(k).to_numpy(np.int64, copy=True)) for k in ("cell_id", "grid_id")
    )
    return {"cell_id": cells, "grid_id": grids, "anchor_db": torch.as_tensor(anchors.to_numpy(np.float32))}


def _anchors_from_state(state: dict[str, Any] | None) -> pd.Series | None:
    if state is None:
        return None
    keys = ("cell_id", "grid_id", "anchor_db")
    if not isinstance(state, dict) or any(k not in state for k in keys):
        raise CheckpointError(
            "the checkpoint's pair anchors are damaged (expected columns cell_id, grid_id, anchor_db)."
        )
    cols = {k: torch.as_tensor(state[k]).reshape(-1).numpy() for k in keys}
    if not len(cols["cell_id"]) == len(cols["grid_id"]) == len(cols["anchor_db"]):
        raise CheckpointError("the checkpoint's pair anchors are damaged (columns of different lengths).")
    if not np.isfinite(cols["anchor_db"]).all():
        raise CheckpointError("the checkpoint's pair anchors are damaged (non-finite values); retrain the model.")
    index = pd.MultiIndex.from_arrays([cols["cell_id"].astype(np.int64), cols["grid_id"].astype(np.int64)],
                                      names=["cell_id", "grid_id"])  # fmt: skip
    return pd.Series(cols["anchor_db"].astype(np.float64), index=index, name="anchor_db")


def _without_removed_options(config: dict[str, Any], config_class: type = RFLSCMConfig) -> dict[str, Any]:
    """A checkpoint's config without the options removed from ``config_class``'s sections (their ``REMOVED``
    tables), if each holds the value now hard-wired; any other value is a one-line :class:`CheckpointError`."""
    config = {k: dict(v) if isinstance(v, dict) else v for k, v in config.items()}
    sections = typing.get_type_hints(config_class)
    for section in dataclasses.fields(config_class):
        removed: dict[str, tuple[Any, str]] = getattr(sections[section.name], "REMOVED", {})
        values = config.get(section.name)
        if not isinstance(values, dict):
            continue
        for key in [k for k in values if k in removed]:
            value = values.pop(key)
            kept, note = removed[key]
            if kept is not ANY and not _same(value, kept):
                raise CheckpointError(
                    f"the checkpoint uses `{section.name}.{key}: {value}`, an option this version no longer has "
                    f"({note}); retrain it with this version."
                )
    return config


def _same(a: Any, b: Any) -> bool:
    """Config values equal, lists and tuples alike."""
    if isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)):
        return list(a) == list(b)
    return bool(a == b)


_OLD_KEYS = (
    (".delta_field.net.", ".fields."),
    (".delta_field.", ".fields.delta_vm."),
    (".feature_field.", ".fields.feature_vm."),
)
"""Stage weight names before the field seam (issue 11) → now: NeRF²'s shared trunk, RF-LSCM's two VM tensors."""


def _current_key(key: str) -> str:
    for old, new in _OLD_KEYS:
        if old in key:
            return key.replace(old, new, 1)
    return key


def _step_and_position(state: dict[str, Any]) -> tuple[int, float]:
    """Steps done and schedule position of a checkpoint's state (before budget mode: ``step − 1``)."""
    step = int(state["step"])
    return step, float(state.get("position", step - 1))


def _changed_keys(a: Any, b: Any, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two nested config dicts."""
    if isinstance(a, dict) and isinstance(b, dict):
        out: list[str] = []
        for key in sorted(set(a) | set(b), key=str):
            out += _changed_keys(a.get(key), b.get(key), f"{prefix}.{key}" if prefix else str(key))
        return out
    return [] if _same(a, b) else [prefix]


@dataclass
class _TrainContext:
    """Training-only tensors: pair data, normalised A (full and coarse columns) and HiTAM's frozen selection."""

    data: PairData
    a_norm: torch.Tensor
    a_coarse: torch.Tensor | None
    num_ssb: int
    """Columns ``0 … num_ssb−1`` of the stacked sensing matrix are SSB beams, the rest CSI-RS beams."""
    selection: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
    """``(bins, valid, known)`` of every training pair once α = 1 (see :meth:`RFLSCM._frozen_selection`)."""


@dataclass
class _Rendered:
    """Training pairs ``pairs [P]`` (sorted) rendered once with the current weights (:meth:`RFLSCM._render_pairs`):
    their predicted round-1 reports ``pred [P, M]`` (normalised, uncorrected) and optionally their strongest
    bins ``top_bins [P, n]`` (int32) with the APS there ``top_x [P, n]``."""

    pairs: torch.Tensor
    pred: torch.Tensor
    top_bins: torch.Tensor | None = None
    top_x: torch.Tensor | None = None

    def rows_of(self, pairs: torch.Tensor) -> torch.Tensor:
        """Rows of ``pairs`` (each one of :attr:`pairs`)."""
        rows = torch.searchsorted(self.pairs, pairs)
        if not bool((self.pairs[rows.clamp_max(max(self.pairs.numel() - 1, 0))] == pairs).all()):
            raise ValueError("pairs that were not rendered")
        return rows


@dataclass
class _PairChunk:
    """A chunk of training pairs ``pairs [B]`` as the pair corrections see them (:meth:`RFLSCM._pair_chunks`):
    ``anchor [B]`` [dB], ``resid [B, M]`` measured − predicted [dB] after the corrections (NaN where not reported),
    ``mask [B, M]`` the reported training beams; with columns, the strongest bins ``top_bins [B, n]``, the APS
    there ``top_x [B, n]``, their columns ``cols [B, M, n]`` and the other bins' ``rest [B, M]`` (normalised)."""

    pairs: torch.Tensor
    anchor: torch.Tensor
    resid: torch.Tensor
    mask: torch.Tensor
    top_bins: torch.Tensor | None = None
    top_x: torch.Tensor | None = None
    cols: torch.Tensor | None = None
    rest: torch.Tensor | None = None

    def fit_inputs(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(cols, top_x, rest)``, the posterior's view of the chunk (made ``with_columns``)."""
        assert self.cols is not None and self.top_x is not None and self.rest is not None
        return self.cols, self.top_x, self.rest
