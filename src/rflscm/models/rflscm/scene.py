"""Scene facts a radiance-field model is built on: cells, the scene box, normalisation, the prior.

Everything here is plain data computed once from a scenario and saved in the checkpoint, so a
loaded model answers :meth:`aps` without the scenario.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from rflscm.errors import ConfigError, DataError, UnsupportedError
from rflscm.fields import PointPrior, density_grid
from rflscm.fields.point_prior import grid_span
from rflscm.fields.surfaces import SurfaceOrientation, structure_grid
from rflscm.models.rflscm.config import SPECULAR_VOXEL_M, RFLSCMConfig
from rflscm.models.rflscm.fields import SceneFrame
from rflscm.render import num_samples_for

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario

ASPRS_BUILDING = 6  # LAS classification code of building points


@dataclass
class SceneInfo:
    """Cells (model order), known grids and the normalisation of a fitted scene."""

    cell_ids: np.ndarray  # int64 [C]
    cell_xyz: np.ndarray  # float64 [C, 3] [m]
    wavelength_m: np.ndarray  # float64 [C]
    grid_ids: np.ndarray  # int64 [G] grids seen in training
    grid_xyz: np.ndarray  # float64 [G, 3]
    r_ref_mw: float  # median reported RSRP [mW]
    a_ref_mw: float  # median over cells of max A [mW per unit gain]
    frame: SceneFrame
    visible: np.ndarray  # bool [C, num_bins]: fine bins a cell's round-1 beams see (render.min_gain_db)

    @property
    def x_ref(self) -> float:
        """Linear path gain of one normalised APS unit, r_ref / a_ref."""
        return self.r_ref_mw / self.a_ref_mw

    def cell_index(self, cell_ids: np.ndarray) -> np.ndarray:
        """Model indices of ``cell_ids``; :class:`UnsupportedError` for cells the model was not fitted on."""
        cell_ids = np.asarray(cell_ids, dtype=np.int64)
        pos = np.clip(np.searchsorted(self.cell_ids, cell_ids), 0, len(self.cell_ids) - 1)
        bad = self.cell_ids[pos] != cell_ids
        if bad.any():
            raise UnsupportedError(
                f"cell(s) {sorted(set(cell_ids[bad].tolist()))[:5]} were not in the training scenario "
                f"(cells: {self.cell_ids.tolist()[:10]}…); retrain with them."
            )
        return pos

    def grid_positions(self, grid_ids: np.ndarray) -> np.ndarray:
        """Positions ``[n, 3]`` of grids seen in training; :class:`UnsupportedError` otherwise."""
        grid_ids = np.asarray(grid_ids, dtype=np.int64)
        pos = np.clip(np.searchsorted(self.grid_ids, grid_ids), 0, max(len(self.grid_ids) - 1, 0))
        if len(self.grid_ids) == 0 or (self.grid_ids[pos] != grid_ids).any():
            raise UnsupportedError("grid positions are needed for grids the model has not seen (pass grid_xyz).")
        return self.grid_xyz[pos]

    def to_dict(self) -> dict[str, Any]:
        return {
            "cell_ids": self.cell_ids,
            "cell_xyz": self.cell_xyz,
            "wavelength_m": self.wavelength_m,
            "grid_ids": self.grid_ids,
            "grid_xyz": self.grid_xyz,
            "r_ref_mw": self.r_ref_mw,
            "a_ref_mw": self.a_ref_mw,
            "frame": self.frame.to_dict(),
            "visible": self.visible,
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SceneInfo:
        frame = d["frame"]
        frame = SceneFrame(**{**frame, "box_lo": tuple(frame["box_lo"]), "box_hi": tuple(frame["box_hi"])})
        return cls(**{**d, "frame": frame})


def visible_bins(a_mw: torch.Tensor, min_gain_db: float | None) -> np.ndarray:
    """``[num_cells, num_bins]`` bool: bins where some beam of the cell has a gain within ``min_gain_db`` of
    the cell's peak (all bins when ``None``).  Directions a cell cannot see carry no information about
    its APS and contribute nothing to its RSRP, so they are neither rendered nor trained."""
    gain = a_mw.max(1).values  # [C, N]
    if min_gain_db is None:
        return np.ones(tuple(gain.shape), dtype=bool)
    peak = gain.max(1, keepdim=True).values
    return (gain >= peak * 10.0 ** (min_gain_db / 10.0)).cpu().numpy()


def scene_box(scenario: Scenario, margin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box ``(lo, hi)`` [m] holding the point cloud, the cells and the grids, plus a margin."""
    parts = [
        scenario.cells[1][["x", "y", "z"]].to_numpy(np.float64),
        scenario.grids[["x", "y", "z"]].to_numpy(np.float64),
    ]
    if scenario.point_cloud is not None and len(scenario.point_cloud.xyz):
        parts.append(scenario.point_cloud.xyz)
    pts = np.concatenate(parts)
    lo, hi = pts.min(0) - margin_m, pts.max(0) + margin_m
    return lo, hi


MAX_VOXELS = 100_000_000
"""Most grid points a voxelised scene quantity (point-cloud prior, surface orientation) may have (~400 MB)."""
MAX_SAMPLES_PER_RAY = 50_000
"""Most samples along one ray (scene diagonal / ``render.step_m``)."""


def check_scene_box(cfg: Any, lo: np.ndarray, hi: np.ndarray) -> None:
    """Refuse a scene box that cannot be voxelised (``DataError`` naming the extent and the voxel size).

    ``rflscm check`` refuses implausible coordinates already; this is the model's own guard for a scene
    that passes those limits but is still too large for the configured voxel sizes.
    """
    extent = np.asarray(hi, np.float64) - np.asarray(lo, np.float64)
    size = " × ".join(f"{e:.4g}" for e in extent) + " m"
    if not np.isfinite(extent).all():
        raise DataError(f"the scene box (cells, grids and point cloud) is not finite ({size}); run `rflscm check`.")
    question = "are the cells, grids and point cloud in the same coordinate frame and unit (run `rflscm check`)?"
    hint = f"{question} Otherwise raise"
    grids: list[tuple[str | None, float]] = []
    if getattr(cfg, "prior", None) is not None and cfg.prior.enabled:
        grids.append(("model.prior.voxel_m", cfg.prior.voxel_m))
    grids.append((None, SPECULAR_VOXEL_M))  # the surface-orientation grid of the specular cue
    for key, voxel_m in grids:
        count = float(np.prod(np.maximum(np.ceil(extent / voxel_m) + 1, 2)))
        if count > MAX_VOXELS:
            what = f"`{key}` = {voxel_m:g} m" if key else f"the surface grid's {voxel_m:g} m"
            advice = f"{hint} `{key}`." if key else question
            raise DataError(
                f"the scene box is {size}: at {what} that is {count:.3g} voxels, more than the "
                f"{MAX_VOXELS:.0e} a model can hold; {advice}"
            )
    samples = float(np.linalg.norm(extent)) / cfg.render.step_m
    if samples > MAX_SAMPLES_PER_RAY:
        raise DataError(
            f"the scene box is {size}: at `model.render.step_m` = {cfg.render.step_m:g} m a ray needs "
            f"{samples:.3g} samples, more than {MAX_SAMPLES_PER_RAY}; {hint} `model.render.step_m`."
        )


def make_frame(
    cfg: RFLSCMConfig,
    lo: np.ndarray,
    hi: np.ndarray,
    cell_xyz: np.ndarray,
    wavelengths: np.ndarray,
    pair_distances: np.ndarray,
) -> SceneFrame:
    """Q (enough to reach the farthest corner of the box from every cell), reference wavelength and distance."""
    q = num_samples_for(torch.as_tensor(lo), torch.as_tensor(hi), torch.as_tensor(cell_xyz), cfg.render.step_m)
    return SceneFrame(
        box_lo=(float(lo[0]), float(lo[1]), float(lo[2])),
        box_hi=(float(hi[0]), float(hi[1]), float(hi[2])),
        num_samples=int(q),
        reference_wavelength_m=float(np.median(wavelengths)),
        reference_distance_m=float(max(np.median(pair_distances), cfg.render.step_m)),
    )


def make_prior(cfg: RFLSCMConfig, scenario: Scenario, lo: np.ndarray, hi: np.ndarray) -> PointPrior | None:
    """The point-cloud prior Φ of a scenario, or ``None`` when switched off."""
    if not cfg.prior.enabled:
        return None
    cloud = scenario.point_cloud
    if cloud is None or len(cloud.xyz) == 0:
        raise ConfigError(
            f"scenario {scenario.meta.name!r} has no point cloud but the model's point-cloud prior is on "
            "(`prior.enabled: true`); add `point_cloud:` to scenario.yaml, or train without the prior: "
            "`--set prior.enabled=false` (or `prior: {enabled: false}` in a --config YAML)."
        )
    density, grid_lo, grid_hi = density_grid(cloud.xyz, lo, hi, cfg.prior.voxel_m, cfg.render.step_m)
    occupied = density[density > 0]
    threshold = 0.5 * float(np.median(occupied)) if occupied.size else 1.0  # D_th
    beta = 0.1 / max(threshold, 1e-9)  # Φ jumps from 0.1 to 1 at D_th
    return PointPrior(torch.from_numpy(density), torch.from_numpy(grid_lo), torch.from_numpy(grid_hi), threshold, beta)


def make_surfaces(scenario: Scenario, lo: np.ndarray, hi: np.ndarray, seed: int = 0) -> SurfaceOrientation | None:
    """The scan's surface orientation for the decoder's specular cue; ``None`` when the scenario has no point
    cloud (the cue is then 0)."""
    cloud = scenario.point_cloud
    if cloud is None or len(cloud.xyz) < 3:
        return None
    lo, grid_hi, shape = grid_span(lo, hi, SPECULAR_VOXEL_M)
    grid = structure_grid(cloud.xyz, lo, grid_hi, shape, seed=seed)
    return SurfaceOrientation(torch.from_numpy(grid), torch.from_numpy(lo), torch.from_numpy(grid_hi))


def surfaces_state(surfaces: SurfaceOrientation | None) -> dict[str, Any] | None:
    if surfaces is None:
        return None
    return {
        "grid": torch.from_numpy(surfaces.grid_numpy()).half(),
        "box_lo": surfaces.box_lo.cpu().clone(),
        "box_hi": surfaces.box_hi.cpu().clone(),
    }


def surfaces_from_state(state: dict[str, Any] | None) -> SurfaceOrientation | None:
    if state is None:
        return None
    return SurfaceOrientation(state["grid"].float(), state["box_lo"], state["box_hi"])


def building_targets(
    cfg: RFLSCMConfig, scenario: Scenario, prior: PointPrior, max_points: int = 30_000, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor] | None:
    """Points ``[n, 3]`` near the scan and their building share ``[n]`` ∈ [0, 1] (building-point count over
    D_th), for initialising the attenuation; ``None`` without building-classified points."""
    cloud = scenario.point_cloud
    if cloud is None or cfg.field.building_loss_db is None:
        return None
    building = cloud.xyz[cloud.classification == ASPRS_BUILDING]
    if len(building) == 0:
        return None
    lo, hi = prior.box_lo.cpu().numpy(), prior.box_hi.cpu().numpy()
    density, _, _ = density_grid(building, lo, hi, cfg.prior.voxel_m, cfg.render.step_m)
    total = prior.density_grid[0, 0].permute(2, 1, 0).cpu().numpy()
    cells = np.argwhere(total > 0)
    rng = np.random.default_rng(seed)
    cells = cells[rng.choice(len(cells), size=min(max_points, len(cells)), replace=False)]
    points = lo + cells * cfg.prior.voxel_m
    share = np.clip(density[tuple(cells.T)] / max(prior.threshold, 1e-9), 0.0, 1.0)
    return torch.as_tensor(points, dtype=torch.float32), torch.as_tensor(share, dtype=torch.float32)


def prior_state(prior: PointPrior | None) -> dict[str, Any] | None:
    if prior is None:
        return None
    return {
        "density": prior.density_grid[0, 0].permute(2, 1, 0).cpu().clone(),
        "box_lo": prior.box_lo.cpu().clone(),
        "box_hi": prior.box_hi.cpu().clone(),
        "threshold": prior.threshold,
        "beta": prior.beta,
    }


def prior_from_state(state: dict[str, Any] | None) -> PointPrior | None:
    if state is None:
        return None
    return PointPrior(state["density"], state["box_lo"], state["box_hi"], state["threshold"], state["beta"])
