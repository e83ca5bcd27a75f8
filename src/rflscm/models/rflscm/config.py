"""Typed configuration of RF-LSCM (and of models that reuse its renderer, e.g. NeRF²-LSCM).

``RFLSCMConfig(field, decoder, prior, render, hitam, loss, train, corrections)``; every default is visible
here.  Presets ``quick`` and ``full`` live in ``rflscm/configs/rflscm_{quick,full}.yaml`` and list
only what they change.

Settings that used to be options and are fixed since issue 11 are the module constants below (why each is
fixed: docs/DECISIONS.md, "Knobs removed (issue 11)").  Each section's ``REMOVED`` maps a removed key to the
value now hard-wired (None: none) and a note: a YAML config that sets it is refused naming the note
(:func:`rflscm.config.from_dict`); a checkpoint of an older layout is refused as a whole
(:mod:`rflscm.models.rflscm.checkpoint`).
"""

from __future__ import annotations

import dataclasses
import importlib.resources
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar, Literal

from rflscm.config import from_dict, load_yaml
from rflscm.errors import ConfigError
from rflscm.models.wnomp import WNOMPConfig

PRESETS = ("quick", "full")

# --- fixed settings (options until issue 11) ------------------------------------------------------------------
MAX_RESOLUTION = 256
"""Most grid points per axis of a VM tensor (caps ``field.voxel_m`` on very large scenes)."""
DELTA_BASIS: Literal["per_channel"] = "per_channel"
"""Basis of 𝒢_δ: the loss and index channels on separate factors (see :class:`~rflscm.fields.TensorVM`)."""
FEATURE_BASIS: Literal["per_component"] = "per_component"
"""Basis of 𝒢_R (see :class:`~rflscm.fields.TensorVM`)."""
FEATURE_INIT_SCALE = 0.1
"""Standard deviation of the initial vector/matrix entries of 𝒢_R."""
DELTA_INIT_SCALE = 0.2
"""Standard deviation of the initial vector/matrix entries of 𝒢_δ."""
LEARN_MU = True
"""Re μ ≥ 1 is learned (not fixed at 1)."""
INIT_LOSS_DB = 0.01
"""Per-voxel loss at the reference carrier at raw δ = 0 [dB] (≈ free space)."""
DIR_FREQS = 6
"""Frequencies of PE(ω) and of the (query, sample) pair directions."""
POS_FREQS = 4
"""Frequencies of the PE of the decoder's log-distances."""
GRID_FREQS = 6
"""Frequencies of PE(p_l) (p_l scaled to [−1, 1] over the scene box)."""
WAVELENGTH_FREQS = 1
"""Frequencies of PE(log λ/λ_ref)."""
SPECULAR_POWERS = (1, 4, 16, 64)
"""Powers sⁿ of the specularity s = hᵀ T h fed to the decoder (``offset`` inputs), h the half-vector and T the
point cloud's surface orientation at the sample (:mod:`rflscm.fields.surfaces`): s → 1 where the sample's
surface would mirror the ray onto the grid; high powers give narrow lobes."""
SPECULAR_VOXEL_M = 4.0
"""Spacing of the surface-orientation grid [m]."""
SOURCE_DECAY = 2.0
"""Initial γ of the learnable factor (1 + d₂/w)^−γ on |R|, d₂ the sample-to-grid distance and w the radius of
the ray's cone at the sample (along-ray distance × the bin's angular radius, at least Δr): the grid is the
source (reciprocity), so a voxel's radiance towards the cell falls as the grid leaves the voxel's angular
cell.  It makes an untrained APS point towards the grid."""
INIT_RADIANCE_DB = -30.0
"""|R|² at construction relative to the normalised unit x_ref [dB] (near-zero R), before the level
calibration (:data:`INIT_LEVEL_DB`)."""
INIT_LEVEL_DB = -6.0
"""The untrained model's radiance is rescaled so that its median predicted RSRP sits this far from the median
measured one [dB] (small, but not decades off: the log-amplitude would otherwise need thousands of Adam steps
to climb)."""
MAX_LOG_GAIN = 0.0
"""Passivity guard on the cumulative log |Π δ̃|: capped at 0 (|Π δ̃| ≤ 1; single FDAM factors can exceed 1)."""
MIN_WEIGHT = 1e-5
"""Samples whose |Π δ̃|·Φ is below this are not decoded (NeRF's early ray termination; −100 dB of power)."""
FLOOR_DB = -80.0
"""Predictions are floored at this level relative to the median measured RSRP before logs [dB]."""
VAL_BEAM_FRACTION = 0.25
"""Fraction of a validation pair's reported beams held aside (never trained on)."""
SPARSITY = 1e-3
"""β_pen, the weight of the L1 term on x̃ (the paper's value; issue 28: 0 tied and 1e-2 lost at 10 CPU-minutes)."""


def _positive(where: str, value: float, allow_zero: bool = False) -> None:
    if value < 0 or (value == 0 and not allow_zero):
        raise ConfigError(f"`{where}` must be {'>= 0' if allow_zero else '> 0'} (got {value}).")


@dataclass(frozen=True)
class FieldConfig:
    """The VM tensors 𝒢_δ (μ, ε) and 𝒢_R (latent features 𝓜) and the medium parameterisation."""

    REMOVED: ClassVar[dict[str, tuple[Any, str]]] = {
        "max_resolution": (MAX_RESOLUTION, "issue 11: fixed at 256"),
        "delta_basis": (DELTA_BASIS, "issue 11: always per_channel"),
        "feature_basis": (FEATURE_BASIS, "issue 11: always per_component"),
        "init_scale": (FEATURE_INIT_SCALE, "issue 11: fixed at 0.1"),
        "delta_init_scale": (DELTA_INIT_SCALE, "issue 11: fixed at 0.2"),
        "learn_mu": (LEARN_MU, "issue 11: μ is always learned"),
        "init_loss_db": (INIT_LOSS_DB, "issue 11: fixed at 0.01 dB"),
    }
    """Keys removed from this section → (the value now hard-wired, a note for the error message)."""

    voxel_m: float = 8.0
    """Spacing of the tensors' grid points [m] (final resolution; at most 256 points per axis)."""
    delta_rank: int = 8
    """R₁, rank-1 components per mode of 𝒢_δ."""
    feature_rank: int = 16
    """R₂, rank-1 components per mode of 𝒢_R."""
    feature_dim: int = 16
    """D_R, latent feature channels."""
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
        _positive("model.field.voxel_m", self.voxel_m)
        for name in ("delta_rank", "feature_rank", "feature_dim"):
            if getattr(self, name) < 1:
                raise ConfigError(f"`model.field.{name}` must be >= 1 (got {getattr(self, name)}).")
        if list(self.upsample_at) != sorted(set(self.upsample_at)):
            raise ConfigError(f"`model.field.upsample_at` must be increasing steps (got {list(self.upsample_at)}).")
        if self.upsample_at and (self.init_voxel_m is None or self.init_voxel_m <= self.voxel_m):
            raise ConfigError("`model.field.upsample_at` needs `init_voxel_m` larger than `voxel_m`.")


@dataclass(frozen=True)
class DecoderConfig:
    """The radiance decoder 𝒬(𝓜(p), ω, p_l, λ) → complex R = exp(log |R| + j arg R), times the free-space
    spreading (λ/λ_ref)·(d_ref/d), d = along-ray distance + sample-to-grid distance, and the source factor
    of :data:`SOURCE_DECAY`."""

    REMOVED: ClassVar[dict[str, tuple[Any, str]]] = {
        "dir_freqs": (DIR_FREQS, "issue 11: fixed at 6"),
        "pos_freqs": (POS_FREQS, "issue 11: fixed at 4"),
        "grid_freqs": (GRID_FREQS, "issue 11: fixed at 6"),
        "grid_features": (True, "issue 11: 𝓜(p_l) is always fed"),
        "specular_powers": (SPECULAR_POWERS, "issue 11: always [1, 4, 16, 64]; `inputs: paper` has no cue"),
        "specular_voxel_m": (SPECULAR_VOXEL_M, "issue 11: fixed at 4 m"),
        "wavelength_freqs": (WAVELENGTH_FREQS, "issue 11: fixed at 1"),
        "output": ("polar", "issue 11: always polar"),
        "spreading_prior": (True, "issue 11: always on"),
        "source_decay": (SOURCE_DECAY, "issue 11: fixed at 2"),
        "init_radiance_db": (INIT_RADIANCE_DB, "issue 11: fixed at -30 dB"),
        "init_level_db": (INIT_LEVEL_DB, "issue 11: fixed at -6 dB"),
        "grid_code_dim": (0, "issue 11: per-grid codes are gone"),
        "grid_code_neighbours": (None, "issue 11: per-grid codes are gone"),
    }
    """Keys removed from this section → (the value now hard-wired, a note for the error message)."""

    hidden: int = 64
    layers: int = 2
    inputs: Literal["paper", "offset", "offset+grid"] = "offset+grid"
    """``paper``: [𝓜(p), PE(ω), PE(p_l), PE(λ)] (plus 𝓜(p_l), a learned code of the grid's surroundings);
    ``offset`` replaces PE(p_l) by the direction from the sample to the grid, the half-vector between it and
    −ω (the surface normal of a specular reflection), the log-distances from the sample to the grid (also
    relative to the ray's cone) and along the ray, and the specular cue of :data:`SPECULAR_POWERS`;
    ``offset+grid`` feeds both."""

    @property
    def grid_position_input(self) -> bool:
        """The decoder reads the grid's normalised position (``paper``, ``offset+grid``)."""
        return self.inputs in ("paper", "offset+grid")

    @property
    def pair_geometry_input(self) -> bool:
        """The decoder reads the sample-to-grid geometry (``offset``, ``offset+grid``)."""
        return self.inputs in ("offset", "offset+grid")

    def __post_init__(self) -> None:
        if self.hidden < 1 or self.layers < 1:
            raise ConfigError(f"`model.decoder` needs hidden >= 1 and layers >= 1 (got {self.hidden}, {self.layers}).")


@dataclass(frozen=True)
class PriorConfig:
    """The point-cloud prior Φ (paper §III-D): point counts D(p) within Δr of each grid point; Φ = 1 above
    the threshold D_th (half the median count of the grid points that have any: it adapts to the scan's
    point density, which differs by orders of magnitude between scanners), Φ = β·D below it with
    β = 0.1 / D_th.  Samples with Φ = 0 are skipped (exact: they are inert)."""

    REMOVED: ClassVar[dict[str, tuple[Any, str]]] = {
        "radius_m": (None, "issue 11: always the ray step Δr"),
        "density_threshold": (None, "issue 11: always half the median occupied count"),
        "beta": (None, "issue 11: always 0.1 / D_th"),
        "skip_below": (0.0, "issue 11: only Φ = 0 samples are skipped"),
    }
    """Keys removed from this section → (the value now hard-wired, a note for the error message)."""

    enabled: bool = True
    voxel_m: float = 2.0
    """Spacing of the density grid D(p) [m]."""

    def __post_init__(self) -> None:
        _positive("model.prior.voxel_m", self.voxel_m)


@dataclass(frozen=True)
class RenderConfig:
    """Ray sampling and the APS integral (paper: Π_{q̃≤q} δ̃, the cumulative gain capped at 1; Q samples, enough
    to reach the farthest corner of the scene box from every cell; early ray termination below
    :data:`MIN_WEIGHT`)."""

    REMOVED: ClassVar[dict[str, tuple[Any, str]]] = {
        "num_samples": (None, "issue 11: always enough to cross the scene box"),
        "inclusive": (True, "issue 11: always the paper's Π_{q̃≤q}"),
        "max_log_gain": (MAX_LOG_GAIN, "issue 11: |Π δ̃| is always capped at 1"),
        "min_weight": (MIN_WEIGHT, "issue 11: fixed at 1e-5"),
        "coherent": (True, "issue 11: the sum along a ray is always coherent"),
    }
    """Keys removed from this section → (the value now hard-wired, a note for the error message)."""

    step_m: float = 4.0
    """Δr, the sample spacing and FDAM voxel thickness d [m]."""
    min_gain_db: float | None = -30.0
    """Directions where every round-1 beam of a cell is this far below the cell's peak gain are not
    rendered for that cell (they cannot affect its RSRP); null renders the whole sphere."""
    chunk_samples: int = 262_144
    """Decoder evaluations per chunk at inference (bounds memory; results do not depend on it)."""

    def __post_init__(self) -> None:
        _positive("model.render.step_m", self.step_m)
        if self.chunk_samples < 1:
            raise ConfigError(f"`model.render.chunk_samples` must be >= 1 (got {self.chunk_samples}).")


@dataclass(frozen=True)
class HiTAMConfig:
    """Hierarchical tensor angular modelling (paper §IV-B).  At the end of the warm-up the refinement model
    starts as a copy of the coarse one, rescaled so that its median error on a few training pairs matches
    the coarse model's."""

    REMOVED: ClassVar[dict[str, tuple[Any, str]]] = {
        "fine_init": ("copy_coarse", "issue 11: the refinement model always starts from the coarse one"),
        "coarse_bins": ("block", "issue 11: always block sums"),
        "selection": (
            "power",
            "issue 28: the coarse fill, `hitam.outside: coarse`, gains as much without its costlier renders",
        ),
    }
    """Keys removed from this section → (the value now hard-wired, a note for the error message)."""

    enabled: bool = True
    beta: int = 3
    """Coarse bins are every beta-th fine bin on both axes."""
    top_k: int = 32
    """K_C, coarse bins refined per (cell, grid)."""
    warmup_steps: int = 1000
    """Coarse-only steps before α starts rising."""
    ramp_steps: int = 500
    """Steps over which α rises linearly from 0 to 1."""
    outside: Literal["zero", "coarse"] = "coarse"
    """The model's APS outside the refined blocks Ω′ once the refinement model has trained: ``zero`` (the paper's
    form) or ``coarse`` (the default), the coarse model's power in the
    :data:`~rflscm.models.rflscm.renderer.FILL_BLOCKS` × K_C blocks HiTAM ranks next, spread evenly over each block's
    bins.  Training is the same either way; the pass after training and every prediction read the fill
    (docs/DECISIONS.md, "The coarse fill outside Ω′" and "The coarse fill becomes the default")."""

    def __post_init__(self) -> None:
        if self.beta < 2:
            raise ConfigError(f"`model.hitam.beta` must be >= 2 (got {self.beta}).")
        if self.top_k < 1:
            raise ConfigError(f"`model.hitam.top_k` must be >= 1 (got {self.top_k}).")
        _positive("model.hitam.warmup_steps", self.warmup_steps, allow_zero=True)
        _positive("model.hitam.ramp_steps", self.ramp_steps, allow_zero=True)


@dataclass(frozen=True)
class LossConfig:
    """The training loss; predictions are floored at :data:`FLOOR_DB` below the median measured RSRP."""

    REMOVED: ClassVar[dict[str, tuple[Any, str]]] = {
        "floor_db": (FLOOR_DB, "issue 11: fixed at -80 dB"),
        "sparsity": (SPARSITY, "issue 28: fixed at the paper's 1e-3; 0 tied and 1e-2 lost"),
    }
    """Keys removed from this section → (the value now hard-wired, a note for the error message)."""

    fidelity: Literal["linear", "log", "shape"] = "log"
    """‖r − A x̃‖² in normalised linear power (paper), in bels (dB/10), or in bels after each pair's own level
    (``shape``: the predictions of each pair first move by all but the share
    :data:`~rflscm.models.rflscm.losses.LEVEL_KEPT` of its mean error on its reports, so the field learns the pairs'
    relative beam levels and the anchors after training their levels; better at 10 CPU-minutes and level or better
    in the demos of three scenes, but the field's own level then predicts grids without reports worse, B6 field's
    SSB / CSI-RS by 0.29 / 0.08 dB over four training seeds, SSB then under half of B6's distance closed: docs/DECISIONS.md)."""
    missing_penalty: float = 0.5
    """α_P (one-sided penalty on missing beams predicted above r_th)."""

    def __post_init__(self) -> None:
        _positive("model.loss.missing_penalty", self.missing_penalty, allow_zero=True)


@dataclass(frozen=True)
class TrainConfig:
    REMOVED: ClassVar[dict[str, tuple[Any, str]]] = {
        "calibrate_levels": (True, "issue 24: moved to `corrections.calibrate_levels`"),
        "pair_anchors": (True, "issue 24: moved to `corrections.pair_anchors`"),
        "pair_posterior": (True, "issue 24: moved to `corrections.pair_posterior`"),
        "val_beam_fraction": (VAL_BEAM_FRACTION, "issue 11: fixed at 0.25"),
    }
    """Keys removed from this section → (the value now hard-wired, a note for the error message)."""

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
    finish_share: float = 0.5
    """In a time-budget run, the pass after training (the pair corrections) may take at most this share of the
    budget; where the model measures that it needs more, the pass covers the pairs that fit in it and the others
    get WNOMP's APS of their reports or the level correction only (``corrections.wnomp_fallback``)."""
    val_pairs: int = 128
    """Pairs with held-aside round-1 beams (a quarter of each pair's reported beams, never trained on) for the
    running validation MAE (0: none)."""
    val_every: int = 100
    checkpoint_every: int = 500
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("steps", "batch_pairs", "pairs_per_cell", "val_every", "checkpoint_every"):
            if getattr(self, name) < 1:
                raise ConfigError(f"`train.{name}` must be >= 1 (got {getattr(self, name)}).")
        if not 0 < self.lr_decay <= 1:
            raise ConfigError(f"`train.lr_decay` must be in (0, 1] (got {self.lr_decay}).")
        if not 0 < self.finish_share < 1:
            raise ConfigError(f"`train.finish_share` must be in (0, 1) (got {self.finish_share}).")
        for name, value in self.lr.items():
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise ConfigError(
                    f"`train.lr.{name}` must be a number (got {value!r}; write 1.0e-3, not 1e-3, in YAML)."
                )
            _positive(f"train.lr.{name}", value)


@dataclass(frozen=True)
class CorrectionsConfig:
    """The post-training pair corrections (:mod:`~rflscm.models.rflscm.corrections`); training is unchanged."""

    calibrate_levels: bool = True
    """Correct each cell's SSB and CSI-RS predictions by the median error on its reported round-1 beams, measured
    after training (:mod:`~rflscm.models.rflscm.corrections`); the training itself is unchanged."""
    pair_anchors: bool = True
    """Move each training pair's (cell, grid) predictions, in every round, by the mean error [dB] that remains on
    its own reported round-1 beams (:mod:`~rflscm.models.rflscm.corrections`): the field gives the
    angular shape and what a changed antenna does, the pair's own reports its level.  Where a pair has no
    posterior, that mean is pulled toward its cell's mean anchor by how much its few reports say
    (:mod:`~rflscm.models.rflscm.anchors`).  Measured after training; pairs without round-1 reports (unseen
    grids) keep the field's level."""
    pair_posterior: bool = True
    """Refine each training pair's APS on its own reported round-1 beams: per-bin gains on the field's strongest
    bins under a ridge prior centred on the field, the ridge chosen on held-aside reports (off when no choice
    beats the field there; :mod:`~rflscm.models.rflscm.posterior`).  Measured after training, like the anchors; pairs
    without round-1 reports keep the field's APS."""
    wnomp_atoms: bool = True
    """Add WNOMP's support of each training pair's reports (its atoms through the model's own sensing columns) to
    the posterior's candidate bins, each centred on the field's value there or, where the field has less, on
    WNOMP's or 10 dB below it (:func:`~rflscm.models.rflscm.posterior.with_atoms`): the field's strongest bins can
    miss the direction that a grid's reports point at.  How many atoms (2, 4 or none) and the centre are chosen
    with λ on held-aside reports.  Where a posterior is chosen, its predictions are also averaged in dB with WNOMP's
    APS of the pair's reports, with a weight chosen per group on held-aside reports
    (:data:`~rflscm.models.rflscm.corrections.MIX_WEIGHTS`).  Needs ``pair_posterior``."""
    wnomp_fallback: bool | WNOMPConfig = True
    """Within a time budget, the training pairs that the pass after training cannot reach get WNOMP's APS of their
    own round-1 reports (no render; :mod:`~rflscm.models.rflscm.fallback`) instead of the field with its level,
    when that predicts the held-aside reports of the rendered pairs better.  True: with WNOMP's default settings
    (what ``rflscm train --model wnomp`` fits); a mapping of WNOMP settings (``k_max``, ``weighting``,
    ``tolerance``, ``residual_floor``, …): with those (``rflscm demo`` gives the ones its WNOMP baseline selected,
    so that such a pair is answered as the baseline answers it); False: off.  Without a budget every pair is reached
    and this does nothing."""
    lambda_groups: int = 3
    """The posterior's λ, WNOMP atoms and their prior centre are chosen on held-aside reports per group of pairs
    with about as many reports (this many groups of about equal size among the pairs λ is chosen on, by report
    count): a pair with many reports can follow them further than one with few.  1: one choice for all pairs."""

    unseen_blend_grids: float | None = 0.0
    """How a grid without any round-1 report (an unseen grid) is predicted: the model's APS there blended with its
    APS at the cell's nearest anchored grid, (1 − w) × own + w × nearest (linear).  0: w is
    :data:`~rflscm.models.rflscm.corrections.UNSEEN_WEIGHT`; a share in (0, 1): that share of the training grids
    (those with reported round-1 beams) is held out of the field's training and w among 0, 0.1, …, 1 is chosen on
    their reports (:func:`~rflscm.models.rflscm.corrections.choose_blend`; their pairs still get anchors and a
    posterior after training, but the field trains on that share of the grids less); None: no blend."""

    def __post_init__(self) -> None:
        if self.lambda_groups < 1:
            raise ConfigError(f"`model.corrections.lambda_groups` must be >= 1 (got {self.lambda_groups}).")
        if self.unseen_blend_grids is not None and not 0.0 <= self.unseen_blend_grids < 1.0:
            raise ConfigError(
                f"`model.corrections.unseen_blend_grids` must lie in [0, 1) (got {self.unseen_blend_grids})."
            )


@dataclass(frozen=True)
class RFLSCMConfig:
    field: FieldConfig = dataclasses.field(default_factory=FieldConfig)
    decoder: DecoderConfig = dataclasses.field(default_factory=DecoderConfig)
    prior: PriorConfig = dataclasses.field(default_factory=PriorConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    hitam: HiTAMConfig = dataclasses.field(default_factory=HiTAMConfig)
    loss: LossConfig = dataclasses.field(default_factory=LossConfig)
    train: TrainConfig = dataclasses.field(default_factory=TrainConfig)
    corrections: CorrectionsConfig = dataclasses.field(default_factory=CorrectionsConfig)


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
