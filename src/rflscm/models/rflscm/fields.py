"""One radiance-field APS model (a "stage": HiTAM has a coarse and a refinement one).

A stage owns its :class:`SceneFields` (raw δ channels → passive (μ, ε) → FDAM, and the feature
field 𝓜), the radiance decoder 𝒬, and renders x̃ (normalised, x / x_ref) for a batch of rays,
each ray conditioned on its grid position and carrier (paper eq. (18)).

**The field seam.**  :class:`SceneFields` is the one place where a field representation plugs in:
RF-LSCM's :class:`VMFields` (two VM tensors) or NeRF²'s MLP (:mod:`rflscm.models.nerf2`).  A model
gets its fields from a :class:`FieldFactory` given at construction
(:class:`~rflscm.models.rflscm.RFLSCM`'s ``fields`` argument); everything else — rays, prior,
FDAM, decoder, HiTAM, losses, checkpoints — is shared.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Protocol

import torch
from torch import nn

from rflscm.fields import (
    MLP,
    PassiveMedium,
    TensorVM,
    encoded_dim,
    fdam_attenuation,
    modulate,
    positional_encoding,
    positional_encoding_t,
    resolution_for,
)
from rflscm.fields.surfaces import specularity
from rflscm.models.rflscm.config import (
    DELTA_BASIS,
    DELTA_INIT_SCALE,
    DIR_FREQS,
    FEATURE_BASIS,
    FEATURE_INIT_SCALE,
    GRID_FREQS,
    INIT_RADIANCE_DB,
    MAX_LOG_GAIN,
    MAX_RESOLUTION,
    MIN_WEIGHT,
    POS_FREQS,
    SOURCE_DECAY,
    SPECULAR_POWERS,
    WAVELENGTH_FREQS,
    DecoderConfig,
    FieldConfig,
    RenderConfig,
)
from rflscm.render import PackedSamples, accumulate_power, join_queries, transmittance

DECODER_BLOCK = 8192
"""(query, sample) pairs the decoder evaluates at a time without gradients on a CPU: its per-pair tensors (the widest,
``[J, hidden]`` and the pair inputs) then stay about 2–4 MB (issue 29: 8192 measured fastest of 2048…32768 and all
at once; the results do not depend on it)."""


@dataclass(frozen=True)
class SceneFrame:
    """Scene constants the fields and the decoder are built on (saved in checkpoints)."""

    box_lo: tuple[float, float, float]
    box_hi: tuple[float, float, float]
    num_samples: int
    """Q, samples per ray."""
    reference_wavelength_m: float
    reference_distance_m: float
    """Typical cell-to-grid distance d_ref [m] (decoder input scale, spreading prior)."""

    def to_dict(self) -> dict:
        return asdict(self)


class SceneFields(nn.Module):
    """The fields of a stage: raw δ channels (→ :class:`~rflscm.fields.PassiveMedium`) and features 𝓜.

    A point set is first *encoded* once (:meth:`encode`); δ and 𝓜 are then read from that code, so a
    representation whose two fields share a trunk (NeRF²) evaluates it once per sample.  The stage
    asks δ of every stored sample and 𝓜 of the live ones (rows of the same code).
    """

    feature_dim: int

    def encode(self, points: torch.Tensor) -> torch.Tensor:
        """Per-point code ``[S, ·]`` of world points ``[S, 3]`` [m] (the points themselves by default)."""
        return points

    def delta(self, code: torch.Tensor) -> torch.Tensor:
        """Raw δ channels ``[S, C_δ]`` of encoded points."""
        raise NotImplementedError

    def features(self, code: torch.Tensor) -> torch.Tensor:
        """Features ``[S, feature_dim]`` of encoded points."""
        raise NotImplementedError

    def delta_module(self) -> nn.Module:
        """The module whose parameters determine δ (fitted by the attenuation initialisation, and copied
        from one stage to the other)."""
        raise NotImplementedError


class FieldFactory(Protocol):
    """Builds a stage's :class:`SceneFields` for a scene frame; says how the decoder's head is sized and when
    the fields' resolution grows."""

    head_hidden: int | None
    """Width of the decoder's layers after the first (None: the decoder's ``hidden``)."""
    upsample_at: tuple[int, ...]
    """Training steps at which :meth:`resolution` grows (empty: fixed)."""

    def __call__(self, frame: SceneFrame, delta_channels: int) -> SceneFields: ...

    def resolution(self, frame: SceneFrame, level: int) -> tuple[int, int, int] | None:
        """Tensor resolution after ``level`` upsamplings (None: the fields have none)."""
        ...


class VMFields(SceneFields):
    """RF-LSCM's fields: 𝒢_δ and 𝒢_R as two :class:`~rflscm.fields.TensorVM` over the scene box."""

    def __init__(self, delta_vm: TensorVM, feature_vm: TensorVM) -> None:
        super().__init__()
        self.delta_vm, self.feature_vm = delta_vm, feature_vm
        self.feature_dim = feature_vm.out_dim

    def delta(self, code: torch.Tensor) -> torch.Tensor:
        return self.delta_vm(code)

    def features(self, code: torch.Tensor) -> torch.Tensor:
        return self.feature_vm(code)

    def delta_module(self) -> nn.Module:
        return self.delta_vm


class VMFieldFactory:
    """:class:`FieldFactory` of :class:`VMFields` from RF-LSCM's ``field`` section."""

    head_hidden: int | None = None

    def __init__(self, cfg: FieldConfig) -> None:
        self.cfg = cfg
        self.upsample_at = tuple(cfg.upsample_at)

    def voxel_m(self, level: int) -> float:
        """Tensor spacing after ``level`` upsamplings (geometric from ``init_voxel_m`` to ``voxel_m``)."""
        f = self.cfg
        if not f.upsample_at or f.init_voxel_m is None:
            return f.voxel_m
        return f.init_voxel_m * (f.voxel_m / f.init_voxel_m) ** (level / len(f.upsample_at))

    def resolution(self, frame: SceneFrame, level: int) -> tuple[int, int, int]:
        lo, hi = torch.tensor(frame.box_lo), torch.tensor(frame.box_hi)
        return resolution_for(lo, hi, self.voxel_m(level), MAX_RESOLUTION)

    def __call__(self, frame: SceneFrame, delta_channels: int) -> VMFields:
        f = self.cfg
        lo, hi = torch.tensor(frame.box_lo), torch.tensor(frame.box_hi)
        res = self.resolution(frame, 0)
        delta = TensorVM(lo, hi, res, f.delta_rank, delta_channels, DELTA_BASIS, DELTA_INIT_SCALE)
        features = TensorVM(lo, hi, res, f.feature_rank, f.feature_dim, FEATURE_BASIS, FEATURE_INIT_SCALE)
        return VMFields(delta, features)


@dataclass
class RayBatch:
    """Rays of one batch: a cell's antenna position, a direction and the cell's carrier."""

    origin: torch.Tensor  # [R, 3] cell antenna position [m]
    direction: torch.Tensor  # [R, 3] unit vectors (world ENU)
    wavelength_m: torch.Tensor  # [R]
    radius_rad: torch.Tensor  # [R] angular radius of the ray's bin (its cone) [rad]


@dataclass
class Queries:
    """What to render: ray ``ray[q]`` as seen from grid ``grid_xyz[q]``; several queries may share a ray."""

    ray: torch.Tensor  # long [Qn]
    grid_xyz: torch.Tensor  # [Qn, 3] [m]


@dataclass
class _RayPart:
    """What the decoder computes once per sample or per query, before the per-(query, sample) part."""

    sample: torch.Tensor  # [L, hidden] first layer's per-sample part (with its bias)
    query: torch.Tensor  # [Qn, hidden] first layer's per-query part
    radius: torch.Tensor  # [Qn] cone radius of the query's ray [rad]
    direction: torch.Tensor | None  # [Qn, 3] the query's ray direction (pair inputs only)
    log_wl: torch.Tensor  # [Qn] log(λ / λ_ref)


class RadianceDecoder(nn.Module):
    """𝒬: [𝓜(p), PE(ω), conditioning on the grid and λ] → complex R (2 outputs).

    The first layer is split by what its inputs depend on: the sample (𝓜(p)), the query
    (PE(ω), PE(log λ/λ_ref), PE(p_l) for ``paper``/``offset+grid``, 𝓜(p_l)) and, for
    ``offset``/``offset+grid``, the (query, sample) pair: PE of the direction to the grid, of the
    half-vector between it and −ω, of three log-distances (to the grid, along the ray, and to the grid
    relative to the ray's cone radius) and the specular cue.  The sum equals one linear layer over the
    concatenation, but each part is computed once.  Output: (log |R|, arg R), times the spreading factors
    of :class:`~rflscm.models.rflscm.config.DecoderConfig`.
    """

    box_lo: torch.Tensor
    box_hi: torch.Tensor

    def __init__(
        self, cfg: DecoderConfig, feature_dim: int, frame: SceneFrame, step_m: float, head_hidden: int | None = None
    ) -> None:
        """``head_hidden``: width of the layers after the first (default ``cfg.hidden``; NeRF²'s radiance
        head narrows to 128)."""
        super().__init__()
        self.cfg, self.frame, self.step_m = cfg, frame, step_m
        query_width = encoded_dim(3, DIR_FREQS) + encoded_dim(1, WAVELENGTH_FREQS) + feature_dim  # + 𝓜(p_l)
        if cfg.grid_position_input:
            query_width += encoded_dim(3, GRID_FREQS)
        self.sample_in = nn.Linear(feature_dim, cfg.hidden)
        self.query_in = nn.Linear(query_width, cfg.hidden, bias=False)
        self.pair_in = None
        if cfg.pair_geometry_input:
            width = 2 * encoded_dim(3, DIR_FREQS) + encoded_dim(3, POS_FREQS) + len(SPECULAR_POWERS)
            self.pair_in = nn.Linear(width, cfg.hidden, bias=False)
        self.mlp = MLP(cfg.hidden, 2, hidden=head_hidden or cfg.hidden, num_layers=cfg.layers - 1, out_scale=0.1)
        self.source_decay = nn.Parameter(torch.tensor(float(SOURCE_DECAY)))
        self.register_buffer("box_lo", torch.tensor(frame.box_lo, dtype=torch.float32))
        self.register_buffer("box_hi", torch.tensor(frame.box_hi, dtype=torch.float32))
        self.log_amp0 = INIT_RADIANCE_DB / 20.0 * math.log(10.0)

    def _query_inputs(self, rays: RayBatch, queries: Queries, grid_features: torch.Tensor) -> torch.Tensor:
        log_wl = torch.log(rays.wavelength_m / self.frame.reference_wavelength_m)[queries.ray, None]
        parts = [
            positional_encoding(rays.direction[queries.ray], DIR_FREQS),
            positional_encoding(log_wl, WAVELENGTH_FREQS),
        ]
        if self.cfg.grid_position_input:
            unit = 2.0 * (queries.grid_xyz - self.box_lo) / (self.box_hi - self.box_lo) - 1.0
            parts.append(positional_encoding(unit, GRID_FREQS))
        parts.append(grid_features)
        return torch.cat(parts, dim=-1)

    def _pair_inputs(
        self,
        to_grid: torch.Tensor,
        dist: torch.Tensor,
        along: torch.Tensor,
        miss: torch.Tensor,
        direction: torch.Tensor,
        surface: torch.Tensor | None,
    ) -> torch.Tensor:
        """Per (query, sample) inputs ``[J, ·]``: PE of the unit vector to the grid, of the half-vector
        (∥ the surface normal of a specular reflection), of the scaled log-distances and sⁿ of the
        specularity s = hᵀ T h given the structure tensors ``surface [J, 6]`` (0 without them).

        Pure geometry (no parameter reaches it), so it is built without a graph, each part written into its
        rows of one transposed buffer (returned as its ``.T`` view): the largest tensor of a step is written
        once, not concatenated twice."""
        scale = math.log1p(self.frame.reference_distance_m / self.step_m)
        with torch.no_grad():
            logs = torch.stack((torch.log1p(dist / self.step_m), torch.log1p(along / self.step_m), miss), -1) / scale
            half = to_grid - direction
            half = half / half.norm(dim=-1, keepdim=True).clamp_min(1e-6)
            assert self.pair_in is not None
            out = to_grid.new_empty(self.pair_in.in_features, to_grid.shape[0])  # transposed: parts in whole rows
            row = 2 * encoded_dim(3, DIR_FREQS)
            positional_encoding_t(torch.stack((to_grid, half)), DIR_FREQS, out[:row])  # both in one pass
            width = encoded_dim(3, POS_FREQS)
            positional_encoding_t(logs, POS_FREQS, out[row : row + width])
            row += width
            if surface is None:
                out[row:] = 0.0
            else:
                spec = specularity(surface, half).clamp(0.0, 1.0)
                for i, p in enumerate(SPECULAR_POWERS):
                    torch.pow(spec, p, out=out[row + i])
        return out.T

    def forward(
        self,
        features: torch.Tensor,
        points: torch.Tensor,
        along_m: torch.Tensor,
        rays: RayBatch,
        queries: Queries,
        join_query: torch.Tensor,
        join_sample: torch.Tensor,
        grid_features: torch.Tensor,
        surface: torch.Tensor | None = None,
        block: int | None = None,
    ) -> torch.Tensor:
        """Complex R ``[J]`` for (query, sample) pairs ``join_query, join_sample [J]``, from per-sample features
        ``[L, D]``, positions ``[L, 3]`` [m], along-ray distances ``[L]`` [m], ``grid_features`` 𝓜(p_l)
        per query ``[Qn, D]`` and with ``surface`` the structure tensors per sample ``[L, 6]``.

        The per-sample and per-query parts of the first layer are computed once; the per-pair part runs over
        the J pairs at once, or ``block`` pairs at a time (inference: every per-pair tensor then stays a few MB,
        in cache and off the page-fault path of fresh large allocations; each pair's value is the same)."""
        ray_part = _RayPart(
            self.sample_in(features),
            self.query_in(self._query_inputs(rays, queries, grid_features)),
            rays.radius_rad[queries.ray],
            rays.direction[queries.ray] if self.pair_in is not None else None,
            torch.log(rays.wavelength_m / self.frame.reference_wavelength_m)[queries.ray],
        )
        num = join_query.numel()
        if block is None or num <= block:
            return self._pairs(ray_part, points, along_m, queries, join_query, join_sample, surface)
        return torch.cat(
            [
                self._pairs(
                    ray_part, points, along_m, queries, join_query[a : a + block], join_sample[a : a + block], surface
                )
                for a in range(0, num, block)
            ]
        )

    def _pairs(
        self,
        part: _RayPart,
        points: torch.Tensor,
        along_m: torch.Tensor,
        queries: Queries,
        join_query: torch.Tensor,
        join_sample: torch.Tensor,
        surface: torch.Tensor | None,
    ) -> torch.Tensor:
        """Complex R of the (query, sample) pairs ``join_query, join_sample`` given the per-sample and per-query
        parts ``part`` (see :meth:`forward`)."""
        # gathers over the J (query, sample) pairs use index_select: 3–5× faster than indexing on CPU
        frame = self.frame
        along = along_m.index_select(0, join_sample)
        offset = queries.grid_xyz.index_select(0, join_query) - points.index_select(0, join_sample)
        dist = offset.norm(dim=-1).clamp_min(1e-3)
        radius = part.radius.index_select(0, join_query)
        footprint = (along * radius).clamp_min(self.step_m)  # cone radius [m]
        miss = torch.log1p(dist / footprint)  # how far the grid lies outside the ray's cone
        # [J, hidden] is the widest tensor of a step: summed and rectified in place (no op here needs its output
        # kept for the backward pass but the ReLU, which keeps its own result)
        hidden = part.sample.index_select(0, join_sample)
        hidden += part.query.index_select(0, join_query)
        if self.pair_in is not None:
            assert part.direction is not None
            direction = part.direction.index_select(0, join_query)
            surface_j = None if surface is None else surface.index_select(0, join_sample)
            pair = self._pair_inputs(offset / dist[:, None], dist, along, miss, direction, surface_j)
            if torch.is_grad_enabled():
                hidden += self.pair_in(pair)
            else:  # one BLAS call adds the product in place (the same sums, to the bit; no [J, hidden] temporary)
                hidden.addmm_(pair, self.pair_in.weight.T)
        out = self.mlp(hidden.relu_())  # [J, 2]
        # free-space amplitude ∝ λ / d
        log_wl = part.log_wl.index_select(0, join_query)
        log_spread = log_wl + torch.log(frame.reference_distance_m / (along + dist).clamp_min(self.step_m))
        log_spread = log_spread - self.source_decay * miss  # the grid is the source: (1 + d₂/w)^−γ, w the cone radius
        return torch.exp(torch.complex(out[:, 0] + self.log_amp0 + log_spread, out[:, 1]))

    @torch.no_grad()
    def scale_power(self, factor: float) -> None:
        """Multiply the rendered power of a lone scatterer by ``factor`` (amplitude by √factor)."""
        self.mlp.out.bias[0] += 0.5 * math.log(factor)


class RadianceStage(nn.Module):
    """Fields (δ + FDAM, 𝓜), decoder 𝒬 and the renderer for a batch of rays."""

    def __init__(
        self,
        fields: SceneFields,
        medium: PassiveMedium,
        decoder: RadianceDecoder,
        render_cfg: RenderConfig,
        surfaces: nn.Module | None = None,
    ) -> None:
        super().__init__()
        self.fields, self.decoder = fields, decoder
        self.medium, self.render_cfg = medium, render_cfg
        # the scan's surface orientation (shared by the stages and saved by the model, so not a submodule)
        self.surfaces_fn = surfaces.forward if surfaces is not None else None
        self.decoder_evals = 0
        """Decoder evaluations so far (throughput measurements)."""
        self.min_weight = MIN_WEIGHT
        """Early ray termination threshold on |Π δ̃|·Φ (0 decodes every live sample: exact, for tests)."""

    def forward(self, rays: RayBatch, packed: PackedSamples, queries: Queries) -> torch.Tensor:
        """x̃ ``[num_queries]`` (normalised): rays ``rays`` (stored samples ``packed``) seen from ``queries``.

        Everything along a ray (δ, FDAM, transmittance, 𝓜) is computed once per ray; only the
        decoder runs per (query, sample)."""
        cfg = self.render_cfg
        ray, step = packed.ray, cfg.step_m
        along = packed.index.to(rays.direction.dtype) * step
        points = rays.origin[ray] + along[:, None] * rays.direction[ray]  # p = p_BS + q Δr ω  [S, 3]
        code = self.fields.encode(points)
        mu, eps = self.medium(self.fields.delta(code))
        log_delta = fdam_attenuation(
            mu, eps, rays.wavelength_m[ray], step, log=True, first=packed.first, last=packed.last
        )  # FDAM needs the neighbours, so it runs on every stored sample
        live = (packed.phi > 0).nonzero().squeeze(1)  # the rest is inert (δ̃ = 1, R̃ = 0)
        phi, ray_live = packed.phi[live], ray[live]
        _, log_delta_tilde = modulate(phi, phi, log_delta[live])  # log δ̃ = Φ log δ
        weight = transmittance(log_delta_tilde, ray_live, MAX_LOG_GAIN) * phi  # (Π_{q̃≤q} δ̃)·Φ
        if self.min_weight > 0:  # early ray termination: samples deep behind walls are not decoded
            keep = (weight.detach().abs() > self.min_weight).nonzero().squeeze(1)
            live, weight, ray_live = live[keep], weight[keep], ray_live[keep]
        join_query, join_sample = join_queries(queries.ray, ray_live, packed.num_rays)
        self.decoder_evals += int(join_query.numel())
        features = self.fields.features(code[live])
        grid_features = self.fields.features(self.fields.encode(queries.grid_xyz))
        wants_surface = self.surfaces_fn is not None and self.decoder.pair_in is not None
        surface = self.surfaces_fn(points[live]) if wants_surface and self.surfaces_fn is not None else None
        cpu_inference = not torch.is_grad_enabled() and queries.grid_xyz.device.type == "cpu"
        block = DECODER_BLOCK if cpu_inference else None  # a GPU wants its batches whole
        radiance = self.decoder(
            features, points[live], along[live], rays, queries, join_query, join_sample, grid_features, surface, block
        )
        return accumulate_power(weight.index_select(0, join_sample) * radiance, join_query, queries.ray.numel())


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
