"""Typed configuration of RF-LSCM (and of models that reuse its renderer, e.g. NeRF²-LSCM).

``RFLSCMConfig(field, decoder, prior, render, hitam, loss, train)``; every default is visible
here.  Presets ``quick`` and ``full`` live in ``rflscm/configs/rflscm_{quick,full}.yaml`` and list
only what they change.
"""

from __future__ import annotations

import dataclasses
import importlib.resources
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from rflscm.config import from_dict, load_yaml
from rflscm.errors import ConfigError

PRESETS = ("quick", "full")


def _positive(where: str, value: float, allow_zero: bool = False) -> None:
    if value < 0 or (value == 0 and not allow_zero):
        raise ConfigError(f"`{where}` must be {'>= 0' if allow_zero else '> 0'} (got {value}).")


@dataclass(frozen=True)
class FieldConfig:
    """The VM tensors 𝒢_δ (μ, ε) and 𝒢_R (latent features 𝓜) and the medium parameterisation."""

    voxel_m: float = 8.0
    """Spacing of the tensors' grid points [m] (final resolution, capped by ``max_resolution``)."""
    max_resolution: int = 256
    delta_rank: int = 8
    """R₁, rank-1 components per mode of 𝒢_δ."""
    feature_rank: int = 16
    """R₂, rank-1 components per mode of 𝒢_R."""
    feature_dim: int = 16
    """D_R, latent feature channels."""
    delta_basis: Literal["per_mode", "per_component", "per_channel"] = "per_channel"
    """``per_channel`` keeps the loss and index channels on separate factors (see TensorVM)."""
    feature_basis: Literal["per_mode", "per_component", "per_channel"] = "per_component"
    init_scale: float = 0.1
    """Standard deviation of the initial vector/matrix entries of 𝒢_R."""
    delta_init_scale: float = 0.2
    """Standard deviation of the initial vector/matrix entries of 𝒢_δ."""
    learn_mu: bool = True
    """Learn Re μ ≥ 1; false fixes μ = 1."""
    init_loss_db: float = 0.01
    """Per-voxel loss at the reference carrier at initialisation [dB] (≈ free space)."""
    building_loss_db: float | None = 10.0
    """Initial per-voxel loss [dB] at the reference carrier where the scan's *building* points (ASPRS
    class 6) are dense: the δ field is fitted to this map before training, so walls start opaque and
    ground and free space transparent (the learned loss then only corrects it).  Ignored without a
    classified point cloud or without the prior; null starts from free space everywhere."""
    upsample_at: tuple[int, ...] = ()
    """Training steps at which the tensors' resolution grows (TensoRF-style)."""
    init_voxel_m: float | None = None
    """Starting spacing when ``upsample_at`` is set (geometric steps down to ``voxel_m``)."""

    def __post_init__(self) -> None:
        for name in ("voxel_m", "init_scale", "delta_init_scale", "init_loss_db"):
            _positive(f"model.field.{name}", getattr(self, name))
        for name in ("delta_rank", "feature_rank", "feature_dim"):
            if getattr(self, name) < 1:
                raise ConfigError(f"`model.field.{name}` must be >= 1 (got {getattr(self, name)}).")
        if self.max_resolution < 2:
            raise ConfigError(f"`model.field.max_resolution` must be >= 2 (got {self.max_resolution}).")
        if list(self.upsample_at) != sorted(set(self.upsample_at)):
            raise ConfigError(f"`model.field.upsample_at` must be increasing steps (got {list(self.upsample_at)}).")
        if self.upsample_at and (self.init_voxel_m is None or self.init_voxel_m <= self.voxel_m):
            raise ConfigError("`model.field.upsample_at` needs `init_voxel_m` larger than `voxel_m`.")


@dataclass(frozen=True)
class DecoderConfig:
    """The radiance decoder 𝒬(𝓜(p), ω, p_l, λ) → complex R."""

    hidden: int = 64
    layers: int = 2
    inputs: Literal["paper", "offset", "offset+grid"] = "offset+grid"
    """``paper``: [𝓜(p), PE(ω), PE(p_l), PE(λ)]; ``offset`` replaces PE(p_l) by the direction from the
    sample to the grid, the half-vector between it and −ω (the surface normal of a specular
    reflection), the log-distances from the sample to the grid (also relative to the ray's cone)
    and along the ray; ``offset+grid`` feeds both."""
    dir_freqs: int = 6
    """Frequencies of PE(ω) and of the pair directions (B1 quick subset, 1500 steps: 6 gave SSB MAE 2.98 dB,
    2 gave 3.16, 8 gave 3.20; the refinement stage must tell a block's 3 × 3 bins apart)."""
    pos_freqs: int = 4
    grid_freqs: int = 6
    """Frequencies of PE(p_l) (p_l scaled to [−1, 1] over the scene box)."""
    grid_features: bool = True
    """Also feed 𝓜(p_l), the feature field at the grid: a learned code of the grid's surroundings."""
    specular_powers: tuple[int, ...] = (1, 4, 16, 64)
    """Powers sⁿ of the specularity s = hᵀ T h fed to the decoder (offset inputs only), h the half-vector
    and T the point cloud's surface orientation at the sample (:mod:`rflscm.fields.surfaces`): s → 1
    where the sample's surface would mirror the ray onto the grid; high powers give narrow lobes.
    Empty: no specular cue (the paper's decoder has none; on the B1 quick subset, two seeds, SSB MAE 0.2–0.3 dB
    and CSI-RS 0.2–0.5 dB worse than with it)."""
    specular_voxel_m: float = 4.0
    """Spacing of the surface-orientation grid [m]."""
    wavelength_freqs: int = 1
    output: Literal["polar", "cartesian"] = "polar"
    """``polar``: (log |R|, arg R), suited to the decades of path gain; ``cartesian``: (Re R, Im R)."""
    spreading_prior: bool = True
    """Multiply R by (λ/λ_ref)·(d_ref/d), d = along-ray distance + sample-to-grid distance."""
    source_decay: float = 2.0
    """Initial γ of a learnable factor (1 + d₂/w)^−γ on |R|, d₂ the sample-to-grid distance and w the radius
    of the ray's cone at the sample (along-ray distance × the bin's angular radius, at least Δr): the
    grid is the source (reciprocity), so a voxel's radiance towards the cell falls as the grid leaves
    the voxel's angular cell.  It makes an untrained APS point towards the grid; 0 disables it."""
    init_radiance_db: float = -30.0
    """|R|² at initialisation relative to the normalised unit x_ref [dB] (near-zero R)."""
    init_level_db: float | None = -6.0
    """If set, the untrained model's radiance is rescaled so that its median predicted RSRP sits this
    far from the median measured one [dB] (small, but not decades off: the log-amplitude would
    otherwise need thousands of Adam steps to climb); null keeps ``init_radiance_db``."""

    def __post_init__(self) -> None:
        if self.hidden < 1 or self.layers < 1:
            raise ConfigError(f"`model.decoder` needs hidden >= 1 and layers >= 1 (got {self.hidden}, {self.layers}).")
        for name in ("dir_freqs", "pos_freqs", "grid_freqs", "wavelength_freqs"):
            _positive(f"model.decoder.{name}", getattr(self, name), allow_zero=True)
        _positive("model.decoder.specular_voxel_m", self.specular_voxel_m)
        if any(p < 1 for p in self.specular_powers):
            raise ConfigError(
                f"`model.decoder.specular_powers` must be positive integers (got {list(self.specular_powers)})."
            )


@dataclass(frozen=True)
class PriorConfig:
    """The point-cloud prior Φ (paper §III-D)."""

    enabled: bool = True
    voxel_m: float = 2.0
    """Spacing of the density grid D(p) [m]."""
    radius_m: float | None = None
    """Counting radius [m]; default the ray step Δr (paper)."""
    density_threshold: float | None = None
    """D_th [points]; null: half the median count of the grid points that have any (adapts to the scan's
    point density, which differs by orders of magnitude between scanners)."""
    beta: float | None = None
    """β: Φ = β·D below the threshold; null: 0.1 / D_th (Φ jumps from 0.1 to 1 at the threshold)."""
    skip_below: float = 0.0
    """Samples with Φ ≤ this are skipped (0: only exactly inert samples, an exact shortcut)."""

    def __post_init__(self) -> None:
        _positive("model.prior.voxel_m", self.voxel_m)
        if self.beta is not None:
            _positive("model.prior.beta", self.beta)
        if self.density_threshold is not None:
            _positive("model.prior.density_threshold", self.density_threshold, allow_zero=True)
        _positive("model.prior.skip_below", self.skip_below, allow_zero=True)


@dataclass(frozen=True)
class RenderConfig:
    """Ray sampling and the APS integral."""

    step_m: float = 4.0
    """Δr, the sample spacing and FDAM voxel thickness d [m]."""
    num_samples: int | None = None
    """Q; default: enough to reach the farthest corner of the scene box from every cell."""
    inclusive: bool = True
    """Π_{q̃≤q} (paper) or Π_{q̃<q}."""
    max_log_gain: float | None = 0.0
    """Passivity guard on |Π δ̃| (log): 0 caps it at 1; null disables."""
    min_gain_db: float | None = -30.0
    """Directions where every round-1 beam of a cell is this far below the cell's peak gain are not
    rendered for that cell (they cannot affect its RSRP; ~40 % of the sphere behind a sector
    antenna at −30 dB); null renders the whole sphere."""
    min_weight: float = 1e-5
    """Samples whose |Π δ̃|·Φ is below this are not decoded (NeRF's early ray termination; 1e-5 is
    −100 dB of power: in a one-off profile on the default scenario, ~45 % of the samples a trained model would
    decode lie below it); 0 decodes every live sample."""
    chunk_samples: int = 262_144
    """Decoder evaluations per chunk at inference (memory bound)."""

    def __post_init__(self) -> None:
        _positive("model.render.step_m", self.step_m)
        _positive("model.render.min_weight", self.min_weight, allow_zero=True)
        if self.num_samples is not None and self.num_samples < 1:
            raise ConfigError(f"`model.render.num_samples` must be >= 1 (got {self.num_samples}).")


@dataclass(frozen=True)
class HiTAMConfig:
    """Hierarchical tensor angular modelling (paper §IV-B)."""

    enabled: bool = True
    beta: int = 3
    """Coarse bins are every beta-th fine bin on both axes."""
    top_k: int = 32
    """K_C, coarse bins refined per (cell, grid)."""
    warmup_steps: int = 1000
    """Coarse-only steps before α starts rising."""
    ramp_steps: int = 500
    """Steps over which α rises linearly from 0 to 1."""
    fine_init: Literal["copy_coarse", "fresh"] = "copy_coarse"
    """At the end of the warm-up, start the refinement model from the coarse one (rescaled so that its
    median error on a few training pairs matches the coarse model's) or from scratch."""

    def __post_init__(self) -> None:
        if self.beta < 2:
            raise ConfigError(f"`model.hitam.beta` must be >= 2 (got {self.beta}).")
        if self.top_k < 1:
            raise ConfigError(f"`model.hitam.top_k` must be >= 1 (got {self.top_k}).")
        _positive("model.hitam.warmup_steps", self.warmup_steps, allow_zero=True)
        _positive("model.hitam.ramp_steps", self.ramp_steps, allow_zero=True)


@dataclass(frozen=True)
class LossConfig:
    fidelity: Literal["linear", "log"] = "log"
    """‖r − A x̃‖² in normalised linear power (paper) or in bels (dB/10)."""
    sparsity: float = 1e-3
    """β_pen (L1 on x̃)."""
    missing_penalty: float = 0.5
    """α_P (one-sided penalty on missing beams predicted above r_th)."""
    floor_db: float = -80.0
    """Predictions are floored at this level relative to the median measured RSRP before logs [dB]."""

    def __post_init__(self) -> None:
        _positive("model.loss.sparsity", self.sparsity, allow_zero=True)
        _positive("model.loss.missing_penalty", self.missing_penalty, allow_zero=True)


@dataclass(frozen=True)
class TrainConfig:
    steps: int = 3000
    """Length of the (nominal) schedule: learning-rate decay, and HiTAM's and upsampling's steps, are in its units.
    A step run does this many steps; a time-budget run (``fit(..., budget_s=)``, ``--minutes``) maps its budget
    onto it and does as many steps as fit."""
    batch_pairs: int = 256
    """(cell, grid) pairs per step, drawn across all cells and carriers."""
    pairs_per_cell: int = 8
    """Pairs of a batch come in groups of this many grids of one cell (they share the cell's rays:
    fields along a ray are computed once); 1 draws pairs independently."""
    lr: dict[str, float] = dataclasses.field(default_factory=lambda: {"tensors": 0.01, "networks": 0.001})
    """Adam learning rate per parameter group (names from the model)."""
    lr_decay: float = 0.1
    """Learning rates decay exponentially to this fraction at the last step (1: constant)."""
    val_pairs: int = 128
    """Pairs with held-aside round-1 beams for the running validation MAE (0: none)."""
    val_beam_fraction: float = 0.25
    """Fraction of a validation pair's reported beams held aside (never trained on)."""
    val_every: int = 100
    checkpoint_every: int = 500
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("steps", "batch_pairs", "pairs_per_cell", "val_every", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise ConfigError(f"`train.{name}` must be >= 1 (got {getattr(self, name)}).")
        if not 0 < self.lr_decay <= 1:
            raise ConfigError(f"`train.lr_decay` must be in (0, 1] (got {self.lr_decay}).")
        if not 0 <= self.val_beam_fraction < 1:
            raise ConfigError(f"`train.val_beam_fraction` must be in [0, 1) (got {self.val_beam_fraction}).")
        for name, value in self.lr.items():
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(
                    f"`train.lr.{name}` must be a number (got {value!r}; write 1.0e-3, not 1e-3, in YAML)."
                )
            _positive(f"train.lr.{name}", value)


@dataclass(frozen=True)
class RFLSCMConfig:
    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    decoder: DecoderConfig = dataclasses.field(default_factory=DecoderConfig)
    prior: PriorConfig = dataclasses.field(default_factory=PriorConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    hitam: HiTAMConfig = dataclasses.field(default_factory=HiTAMConfig)
    loss: LossConfig = dataclasses.field(default_factory=LossConfig)
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)


def preset_path(name: str, family: str = "rflscm") -> Path:
    """Path of a shipped preset YAML (``quick`` or ``full``)."""
    return Path(str(importlib.resources.files("rflscm") / "configs" / f"{family}_{name}.yaml"))


def load_rflscm_config(
    config: str | Path | dict[str, Any] | None, cls: type = RFLSCMConfig, family: str = "rflscm"
) -> Any:
    """A config from a preset name, a YAML path, a mapping or ``None`` (the dataclass defaults)."""
    if config is None:
        return cls()
    if isinstance(cls, type) and isinstance(config, cls):
        return config
    if isinstance(config, dict):
        return from_dict(cls, config)
    if isinstance(config, (str, Path)):
        text = str(config)
        if text in PRESETS:
            path = preset_path(text, family)
        elif Path(text).suffix.lower() in (".yaml", ".yml") or Path(text).exists():
            path = Path(text)
        else:
            raise ConfigError(f"unknown config {text!r}: give a preset ({', '.join(PRESETS)}) or a YAML file path.")
        data = load_yaml(path)
        try:
            return from_dict(cls, data)
        except ConfigError as exc:
            raise ConfigError(f"{path}: {exc}") from None
    raise ConfigError(f"a model config must be a preset name, a path or a mapping (got {type(config).__name__}).")
