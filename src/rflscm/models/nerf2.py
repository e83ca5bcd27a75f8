"""NeRF²-LSCM: the RF-LSCM renderer, loss and HiTAM with NeRF²'s MLP fields (SPEC §4, paper §V-B).

NeRF² (Zhao et al., "NeRF²: Neural Radio-Frequency Radiance Fields", MobiCom 2023) represents the
scene with two networks:

* an **attenuation network**: γ(p) (10-frequency positional encoding of the position) → 8 ReLU
  layers of 256 with γ(p) re-injected after layer 4 → the attenuation (here the raw δ channels of
  :class:`~rflscm.fields.PassiveMedium`, so FDAM and its physics are exactly RF-LSCM's) and,
  through a linear *feature layer* 256 → 256, the features of the sample;
* a **radiance head**: [features, conditioning] → 256 → 128 → complex R (2 outputs).  The
  conditioning (ray direction, grid position / offset, carrier) is RF-LSCM's decoder's
  (:class:`~rflscm.models.rflscm.fields.RadianceDecoder`), so only the widths differ.

NeRF²-LSCM *is* :class:`~rflscm.models.rflscm.RFLSCM` with :class:`MLPFieldFactory` plugged into
its one field seam (:class:`~rflscm.models.rflscm.fields.FieldFactory`): ray sampling, the point-cloud
prior, FDAM, the decoder's conditioning, the render integral, the loss, HiTAM, training and
checkpoints are RF-LSCM's.  Presets: ``rflscm/configs/nerf2_{quick,full}.yaml`` (``full`` = the
paper's sizes; ``quick`` shrinks the widths for 2 CPU cores).

The attenuation and the features come from one trunk, evaluated once per stored sample: the
trunk's last hidden layer is the :meth:`~rflscm.models.rflscm.fields.SceneFields.encode` code, from
which the δ head and the feature layer read.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import nn

from rflscm.errors import ConfigError
from rflscm.fields import MLP, encoded_dim, positional_encoding
from rflscm.geometry import AngleGrid
from rflscm.models.base import register_model
from rflscm.models.rflscm import RFLSCM
from rflscm.models.rflscm.config import (
    INIT_LOSS_DB,
    LEARN_MU,
    CorrectionsConfig,
    DecoderConfig,
    HiTAMConfig,
    LossConfig,
    PriorConfig,
    RenderConfig,
    TrainConfig,
)
from rflscm.models.rflscm.fields import SceneFields, SceneFrame


@dataclass(frozen=True)
class NeRF2FieldConfig:
    """NeRF²'s attenuation network (replaces RF-LSCM's VM tensors 𝒢_δ and 𝒢_R); the medium is RF-LSCM's."""

    REMOVED: ClassVar[dict[str, tuple[Any, str]]] = {
        "learn_mu": (LEARN_MU, "issue 11: μ is always learned"),
        "init_loss_db": (INIT_LOSS_DB, "issue 11: fixed at 0.01 dB"),
    }
    """Keys removed from this section → (the value now hard-wired, a note for the error message)."""

    hidden: int = 256
    """Width of the attenuation trunk (NeRF²: 256)."""
    layers: int = 8
    """ReLU layers of the trunk (NeRF²: 8)."""
    skip_at: int | None = 4
    """γ(p) is concatenated to the input of this layer (NeRF²: after layer 4); null: no skip."""
    pos_freqs: int = 10
    """Frequencies of the positional encoding of the position (NeRF²: 10)."""
    feature_dim: int = 256
    """Width of the feature layer feeding the radiance head (NeRF²: 256)."""
    delta_init_scale: float = 0.1
    """Scale of the δ head's initial weights: raw δ ≈ 0 (free space, as RF-LSCM's tensors start)."""
    building_loss_db: float | None = 10.0
    """Initial per-voxel loss [dB] where the scan's building points are dense, fitted before training
    exactly as RF-LSCM does (its ``field.building_loss_db``); null starts from free space."""

    def __post_init__(self) -> None:
        if self.hidden < 1 or self.layers < 1 or self.feature_dim < 1:
            raise ConfigError(
                f"`model.field` needs hidden, layers and feature_dim >= 1 (got {self.hidden}, {self.layers}, {self.feature_dim})."
            )
        if self.skip_at is not None and not 0 < self.skip_at < self.layers:
            raise ConfigError(f"`model.field.skip_at` must lie in 1…{self.layers - 1} or be null (got {self.skip_at}).")
        if self.pos_freqs < 0:
            raise ConfigError(f"`model.field.pos_freqs` must be >= 0 (got {self.pos_freqs}).")
        if self.delta_init_scale < 0:
            raise ConfigError(f"`model.field.delta_init_scale` must be >= 0 (got {self.delta_init_scale}).")
        if self.building_loss_db is not None and self.building_loss_db <= 0:
            raise ConfigError(f"`model.field.building_loss_db` must be > 0 or null (got {self.building_loss_db}).")


@dataclass(frozen=True)
class NeRF2DecoderConfig(DecoderConfig):
    """RF-LSCM's decoder conditioning with NeRF²'s radiance-head widths: in → ``hidden`` → ``head_hidden`` → 2."""

    hidden: int = 256
    layers: int = 2
    head_hidden: int = 128
    """Width of the head's layers after the first (NeRF²: W/2 = 128)."""

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.head_hidden < 1:
            raise ConfigError(f"`model.decoder.head_hidden` must be >= 1 (got {self.head_hidden}).")


@dataclass(frozen=True)
class NeRF2TrainConfig(TrainConfig):
    """RF-LSCM's training settings; one parameter group, ``networks`` (paper §V: lr 0.001 for MLPs)."""

    lr: dict[str, float] = dataclasses.field(default_factory=lambda: {"networks": 0.001})


@dataclass(frozen=True)
class NeRF2Config:
    """NeRF²-LSCM: RF-LSCM's config with ``field`` and ``decoder`` replaced (same keys otherwise)."""

    field: NeRF2FieldConfig = dataclasses.field(default_factory=NeRF2FieldConfig)
    decoder: NeRF2DecoderConfig = dataclasses.field(default_factory=NeRF2DecoderConfig)
    prior: PriorConfig = dataclasses.field(default_factory=PriorConfig)
    render: RenderConfig = dataclasses.field(default_factory=RenderConfig)
    hitam: HiTAMConfig = dataclasses.field(default_factory=HiTAMConfig)
    loss: LossConfig = dataclasses.field(default_factory=LossConfig)
    train: NeRF2TrainConfig = dataclasses.field(default_factory=NeRF2TrainConfig)
    corrections: CorrectionsConfig = dataclasses.field(default_factory=CorrectionsConfig)


class NeRF2Field(SceneFields):
    """γ(p) → 8 × 256 (skip at 4) trunk → (raw δ ``[S, C_δ]``, features ``[S, feature_dim]``).

    The code of a point is the trunk's last hidden layer; positions are normalised to [−1, 1] over the
    scene box before the encoding.
    """

    box_lo: torch.Tensor
    box_hi: torch.Tensor

    def __init__(self, cfg: NeRF2FieldConfig, frame: SceneFrame, delta_channels: int) -> None:
        super().__init__()
        self.cfg = cfg
        self.feature_dim = cfg.feature_dim
        self.register_buffer("box_lo", torch.tensor(frame.box_lo, dtype=torch.float32))
        self.register_buffer("box_hi", torch.tensor(frame.box_hi, dtype=torch.float32))
        in_dim = encoded_dim(3, cfg.pos_freqs)
        # MLP's output layer is the feature layer (linear, no activation, as NeRF²'s feature_layer)
        self.trunk = MLP(in_dim, cfg.feature_dim, hidden=cfg.hidden, num_layers=cfg.layers, skip_at=cfg.skip_at)
        self.delta_head = nn.Linear(cfg.hidden, delta_channels)
        with torch.no_grad():
            self.delta_head.weight.mul_(cfg.delta_init_scale)
            self.delta_head.bias.zero_()

    def encode(self, points: torch.Tensor) -> torch.Tensor:
        """Last hidden layer ``[S, hidden]`` of the trunk at world points ``[S, 3]`` [m]."""
        unit = 2.0 * (points.to(self.box_lo.dtype) - self.box_lo) / (self.box_hi - self.box_lo) - 1.0
        x = positional_encoding(unit, self.cfg.pos_freqs)
        h = x
        for i, layer in enumerate(self.trunk.hidden):
            if self.trunk.skip_at is not None and i == self.trunk.skip_at:
                h = torch.cat((h, x), dim=-1)
            h = torch.relu(layer(h))
        return h

    def delta(self, code: torch.Tensor) -> torch.Tensor:
        return self.delta_head(code)

    def features(self, code: torch.Tensor) -> torch.Tensor:
        return self.trunk.out(code)

    def delta_module(self) -> nn.Module:
        return self  # the trunk feeds both heads


class MLPFieldFactory:
    """The :class:`~rflscm.models.rflscm.fields.FieldFactory` of NeRF²-LSCM: one :class:`NeRF2Field` per stage, the
    decoder's head narrowed to ``head_hidden``, no resolution schedule."""

    upsample_at: tuple[int, ...] = ()

    def __init__(self, cfg: NeRF2FieldConfig, head_hidden: int) -> None:
        self.cfg, self.head_hidden = cfg, head_hidden

    def __call__(self, frame: SceneFrame, delta_channels: int) -> NeRF2Field:
        return NeRF2Field(self.cfg, frame, delta_channels)

    def resolution(self, frame: SceneFrame, level: int) -> None:
        return None


@register_model
class NeRF2LSCM(RFLSCM):
    """NeRF²-LSCM: RF-LSCM with NeRF²'s attenuation MLP and radiance head (:class:`MLPFieldFactory`) instead of VM
    tensors; one parameter group, ``networks``."""

    name: ClassVar[str] = "nerf2"
    config_class: ClassVar[type] = NeRF2Config
    config_family: ClassVar[str] = "nerf2"
    init_fit: ClassVar[tuple[int, float]] = (100, 0.05)
    """The MLP trunk keeps the slower attenuation fit: at RF-LSCM's 0.2 its ReLUs die (no gradient reaches the
    trunk afterwards; ``test_gradient_reaches_every_parameter``)."""

    def __init__(self, config: NeRF2Config, angle_grid: AngleGrid, device: torch.device | str = "cpu") -> None:
        super().__init__(config, angle_grid, device, fields=MLPFieldFactory(config.field, config.decoder.head_hidden))  # type: ignore[arg-type]
