"""RF-LSCM: the radiance-field localized statistical channel model (paper §III–IV, SPEC §3).

``RFLSCM`` implements the model contract (:mod:`rflscm.models.base`).  It owns the ray caches,
HiTAM and the losses; each rendering stage (:class:`~rflscm.models.radiance.RadianceStage`) owns
its fields and decoder.  The fields come from :meth:`RFLSCM.build_fields`, the one method a
NeRF²-style model overrides (MLP fields instead of VM tensors) to reuse the rest.

Units: the stages render the APS in the normalised unit x_ref = r_ref / a_ref (see
:mod:`rflscm.train.data`); :meth:`aps` returns linear path gain.

Decisions where the paper is silent (each switchable in :mod:`~rflscm.models.rflscm_config`):

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
* loss in bels by default (paper: linear), L1 relative to each pair's power scale.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from torch import nn

from rflscm.config import from_dict, to_dict
from rflscm.data import BEAM_TYPES
from rflscm.errors import CheckpointError
from rflscm.fields import PassiveMedium, TensorVM, resolution_for
from rflscm.fields.grid_codes import GridCodes
from rflscm.geometry import AngleGrid
from rflscm.models.base import LSCMModel, discard_partial_save, read_checkpoint, register_model
from rflscm.models.hitam import HiTAM
from rflscm.models.radiance import RadianceDecoder, RadianceStage, SceneFrame
from rflscm.models.rflscm_config import RFLSCMConfig, load_rflscm_config
from rflscm.models.rflscm_render import RenderMixin
from rflscm.models.rflscm_scene import (
    check_scene_box,
    SceneInfo,
    building_targets,
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
from rflscm.train.data import build_pair_data, reference_power, stacked_sensing
from rflscm.train.trainer import Trainer


@register_model
class RFLSCM(RenderMixin, LSCMModel):
    """RF-LSCM with VM-tensor fields, FDAM, the point-cloud prior and HiTAM."""

    name: ClassVar[str] = "rflscm"
    config_class: ClassVar[type] = RFLSCMConfig
    config_family: ClassVar[str] = "rflscm"

    def __init__(self, config: RFLSCMConfig, angle_grid: AngleGrid, device: torch.device | str = "cpu") -> None:
        super().__init__(angle_grid, device)
        self.config = config
        h = config.hitam
        self.hitam = HiTAM(angle_grid, h.beta, h.top_k, h.coarse_bins, h.warmup_steps, h.ramp_steps) if h.enabled else None
        self.scene: SceneInfo | None = None
        self.prior: nn.Module | None = None
        self.surfaces: nn.Module | None = None
        """The scan's surface orientation (decoder's specular cue), or None."""
        self.stages = nn.ModuleDict()
        self.step = 0
        """Training steps done."""
        self.train_state: dict[str, Any] | None = None
        self._cache: dict[str, Any] = {}
        self._train: Any = None

    @classmethod
    def build(cls, config: str | Path | dict[str, Any] | None = None, angle_grid: AngleGrid | None = None,
              device: torch.device | str = "cpu") -> RFLSCM:  # fmt: skip
        """A fresh model from a preset (``"quick"``, ``"full"``), a YAML path, a mapping or ``None``."""
        return cls(load_rflscm_config(config, cls.config_class, cls.config_family), angle_grid or AngleGrid(), device)

    # --- construction (override build_fields to change the field type) -----------------------
    def build_fields(self, frame: SceneFrame) -> tuple[nn.Module, nn.Module]:
        """``(δ field, feature field)``: modules ``[S, 3] → [S, C_δ]`` and ``[S, 3] → [S, D_R]``."""
        f = self.config.field
        lo, hi = torch.tensor(frame.box_lo), torch.tensor(frame.box_hi)
        res = resolution_for(lo, hi, self._voxel_m(0), f.max_resolution)
        channels = self.medium(frame).num_channels
        delta = TensorVM(lo, hi, res, f.delta_rank, channels, f.delta_basis, f.delta_init_scale)
        features = TensorVM(lo, hi, res, f.feature_rank, f.feature_dim, f.feature_basis, f.init_scale)
        return delta, features

    def medium(self, frame: SceneFrame) -> PassiveMedium:
        f = self.config.field
        return PassiveMedium(frame.reference_wavelength_m, self.config.render.step_m, f.learn_mu, f.init_loss_db)

    def _voxel_m(self, level: int) -> float:
        """Tensor spacing after ``level`` upsamplings (geometric from ``init_voxel_m`` to ``voxel_m``)."""
        f = self.config.field
        if not f.upsample_at:
            return f.voxel_m
        return f.init_voxel_m * (f.voxel_m / f.init_voxel_m) ** (level / len(f.upsample_at))

    def _build_stages(self, frame: SceneFrame, code_xyz: torch.Tensor | None = None) -> None:
        """Fresh stages; ``code_xyz [G, 3]`` are the measured grids that own a code (``decoder.grid_code_dim``)."""
        if code_xyz is None:  # loading a checkpoint: the code table takes the checkpoint's size
            code_xyz = torch.zeros(1, 3)

        def stage() -> RadianceStage:
            delta, features = self.build_fields(frame)
            decoder = RadianceDecoder(self.config.decoder, self.config.field.feature_dim, frame, self.config.render.step_m, code_xyz)
            return RadianceStage(delta, features, self.medium(frame), decoder, self.config.render, self.surfaces)

        names = ("coarse", "fine") if self.hitam is not None else ("fine",)
        self.stages = nn.ModuleDict({n: stage() for n in names}).to(self.device)

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]:
        """``{"tensors": VM vectors, matrices and basis vectors and the grid codes, "networks": the decoders}``
        (empty groups dropped)."""
        groups: dict[str, list[nn.Parameter]] = {"tensors": [], "networks": []}
        for module in self.stages.modules():
            if isinstance(module, (TensorVM, GridCodes)):
                groups["tensors"].extend(module.parameters())
        tensor_ids = {id(p) for p in groups["tensors"]}
        groups["networks"] = [p for p in self.stages.parameters() if id(p) not in tensor_ids]
        return {k: v for k, v in groups.items() if v}

    # --- fitting ------------------------------------------------------------------------------
    def _prepare(self, scenario: Any) -> None:
        """Scene facts, normalisation, prior, fresh stages and training data for ``scenario``."""
        cfg = self.config
        torch.manual_seed(cfg.train.seed)
        cell_ids = scenario.cell_ids()
        a_mw, num_ssb = stacked_sensing(scenario, cell_ids, self.angle_grid, device=self.device)
        a_ref = float(a_mw.flatten(1).max(1).values.median())
        r_ref = reference_power(np.concatenate([scenario.rsrp_table(1, t)[1].ravel() for t in BEAM_TYPES]))
        a_norm = a_mw / a_ref
        data = build_pair_data(
            scenario, cell_ids, a_norm, num_ssb, r_ref, cfg.train.val_pairs, cfg.train.val_beam_fraction, cfg.train.seed
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
        self._build_stages(self.scene.frame, torch.unique(data.grid_xyz, dim=0))
        targets = building_targets(cfg, scenario, prior, seed=cfg.train.seed) if prior is not None else None
        if targets is not None:
            self._init_attenuation(*targets)
        self._cache.clear()
        a_coarse = self.hitam.coarse_columns(a_norm) if self.hitam is not None else None
        self._train = _TrainContext(data.to(self.device), a_norm, a_coarse)
        self.step, self.train_state = 0, None
        if cfg.decoder.init_level_db is not None:
            self._calibrate_level(cfg.decoder.init_level_db)

    def fit(self, scenario: Any, progress: bool = True, callback: Any = None,
            checkpoint_path: str | Path | None = None, resume: bool = False) -> dict[str, float]:  # fmt: skip
        """Train on the round-1 measurements of ``scenario`` (see :meth:`LSCMModel.fit`)."""
        discard_partial_save(checkpoint_path)  # a save killed half-way (kill -9) leaves its temporary file behind
        self._prepare(scenario)
        self.fingerprint = scenario.fingerprint()
        d = self._train.data
        train_pairs = torch.nonzero(d.beam_mask.any(1)).squeeze(1).cpu()
        trainer = Trainer(self, self.config.train, train_pairs, groups=d.cell_index.cpu()[train_pairs])
        if resume and checkpoint_path is not None and Path(checkpoint_path).is_file():
            self._resume_from(checkpoint_path, trainer)
        evals0, time0 = self.decoder_evals(), trainer.elapsed_s
        summary = trainer.run(progress=progress, callback=callback, checkpoint_path=checkpoint_path)
        rate = (self.decoder_evals() - evals0) / max(trainer.elapsed_s - time0, 1e-9)
        summary["decoder_evals_per_s"] = rate
        self.run_info.update({"train": {k: float(v) for k, v in summary.items()}, "num_pairs": d.num_pairs})
        return summary

    def _resume_from(self, path: str | Path, trainer: Trainer) -> None:
        payload = read_checkpoint(path)
        state = payload["state"]
        if payload["model"] != self.name:
            raise CheckpointError(
                f"{path}: cannot resume: it holds a {payload['model']!r} model, not {self.name!r}; train {self.name} "
                "into another file, or without --resume to overwrite it."
            )
        if payload["fingerprint"] != self.fingerprint:
            raise CheckpointError(f"{path}: cannot resume: it was trained on another scenario (or other data).")
        ours, theirs = to_dict(self.config), dict(state["config"])
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
        self.step = int(state["step"])
        trainer.load_state_dict(state["train_state"])

    def _init_attenuation(self, points: torch.Tensor, share: torch.Tensor, steps: int = 100) -> None:
        """Fit the δ field so that its per-voxel loss is ``building_loss_db`` to the power ``share`` times
        ``init_loss_db`` to the power 1 − ``share`` (log-linear: free space where ``share`` = 0), other
        channels unchanged; every stage starts from the same fit."""
        f = self.config.field
        points, share = points.to(self.device), share.to(self.device)
        target = share * math.log(f.building_loss_db / f.init_loss_db)  # raw loss channel
        stages = list(self.stages.values())
        field = stages[0].delta_field
        with torch.no_grad():
            keep = field(points)[:, 1:]
        opt = torch.optim.Adam(field.parameters(), lr=0.05)
        for _ in range(steps):
            out = field(points)
            loss = (out[:, 0] - target).square().mean() + (out[:, 1:] - keep).square().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
        for stage in stages[1:]:
            stage.delta_field.load_state_dict(field.state_dict())

    def on_step_begin(self, step: int) -> bool:
        """Upsample the tensors at ``upsample_at``; hand the coarse model to the refinement model at the
        end of the HiTAM warm-up.  True when parameters were replaced."""
        self.step = step
        self.forget_aps()
        f, h = self.config.field, self.config.hitam
        if self.hitam is not None and h.fine_init == "copy_coarse" and step == h.warmup_steps and step > 0:
            self.stages["fine"].load_state_dict(self.stages["coarse"].state_dict())
            self._match_fine_to_coarse()
        if step in f.upsample_at:
            self._cache.pop("selection", None)
            level = list(f.upsample_at).index(step) + 1
            lo, hi = torch.tensor(self.scene.frame.box_lo), torch.tensor(self.scene.frame.box_hi)
            res = resolution_for(lo, hi, self._voxel_m(level), f.max_resolution)
            for module in self.stages.modules():
                if isinstance(module, TensorVM):
                    module.upsample(res)
            return True
        return False

    def decoder_evals(self) -> int:
        """Radiance-decoder evaluations so far (all stages)."""
        return sum(s.decoder_evals for s in self.stages.values())

    # --- persistence --------------------------------------------------------------------------
    def state_dict_for_checkpoint(self) -> dict[str, Any]:
        g = self.angle_grid
        return {
            "config": to_dict(self.config),
            "angle_grid": [g.num_el, g.num_az, g.el_min_deg, g.el_step_deg],
            "scene": self.scene.to_dict() if self.scene is not None else None,
            "prior": prior_state(self.prior),
            "surfaces": surfaces_state(self.surfaces),
            "stages": {k: v.detach().cpu().clone() for k, v in self.stages.state_dict().items()},
            "step": self.step,
            "train_state": self.train_state,
        }

    @classmethod
    def from_checkpoint(cls, state: dict[str, Any], device: torch.device | str = "cpu") -> RFLSCM:
        num_el, num_az, el_min, el_step = state["angle_grid"]
        model = cls(from_dict(cls.config_class, state["config"]), AngleGrid(int(num_el), int(num_az), el_min, el_step), device)
        if state["scene"] is None:
            raise CheckpointError("this checkpoint holds an unfitted model.")
        model.scene = SceneInfo.from_dict(state["scene"])
        prior = prior_from_state(state["prior"])
        model.prior = prior.to(model.device) if prior is not None else None
        surfaces = surfaces_from_state(state.get("surfaces"))
        model.surfaces = surfaces.to(model.device) if surfaces is not None else None
        model._build_stages(model.scene.frame)
        model._load_stage_weights(state["stages"])
        model.step, model.train_state = int(state["step"]), state.get("train_state")
        return model

    def _load_stage_weights(self, weights: dict[str, torch.Tensor]) -> None:
        for name, module in self.stages.named_modules():
            if isinstance(module, TensorVM):
                res = tuple(int(weights[f"{name}.lines.{a}"].shape[2]) for a in range(3))
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
        self.forget_aps()
        self._cache.pop("selection", None)


def _changed_keys(a: Any, b: Any, prefix: str = "") -> list[str]:
    """Dotted keys whose values differ between two nested config dicts."""
    if isinstance(a, dict) and isinstance(b, dict):
        out: list[str] = []
        for key in sorted(set(a) | set(b), key=str):
            out += _changed_keys(a.get(key), b.get(key), f"{prefix}.{key}" if prefix else str(key))
        return out
    same = a == b or (isinstance(a, (list, tuple)) and isinstance(b, (list, tuple)) and list(a) == list(b))
    return [] if same else [prefix]


class _TrainContext:
    """Training-only tensors: pair data, normalised A (full and coarse columns)."""

    def __init__(self, data: Any, a_norm: torch.Tensor, a_coarse: torch.Tensor | None) -> None:
        self.data, self.a_norm, self.a_coarse = data, a_norm, a_coarse
