"""The model contract every LSCM model implements (WNOMP, RF-LSCM, NeRF²-LSCM).

Evaluation only ever calls this contract:

* the trainer's ``fit`` (package ``train``) learns from a scenario's **round-1** measurements (never round 2,
  never ``truth/``), optionally restricted to a subset of grids: iterative models through the
  trainer, closed-form ones through :meth:`LSCMModel.fit`;
* :meth:`LSCMModel.aps` returns the APS of (cell, grid) pairs on the model's
  :class:`~rflscm.geometry.AngleGrid` in linear path-power gain (world frame);
* :meth:`LSCMModel.predict_rsrp` turns APS into RSRP [dBm] for *any* antenna
  configuration through the sensing matrix (r = A′ x), shared by all models;
* :meth:`LSCMModel.save` / :func:`load_model` write and read a single
  checkpoint file holding the config, the weights and the scenario fingerprint.
"""

from __future__ import annotations

import abc
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import pandas as pd
import torch

from rflscm.errors import CheckpointError, UnsupportedError
from rflscm.geometry import AngleGrid

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario

MIN_POWER_MW = 1e-30  # floor before taking dB of a predicted RSRP

__all__ = [
    "MIN_POWER_MW",
    "MODEL_REGISTRY",
    "LSCMModel",
    "TrainingPlan",
    "UnsupportedError",
    "load_model",
    "read_checkpoint",
    "register_model",
]


@dataclass
class TrainingPlan:
    """What an iteratively trained model's ``prepare`` hands the trainer (the trainer's ``Trainable`` protocol):
    the pairs to draw batches from and their group keys."""

    pairs: torch.Tensor
    """long ``[P]``: indices of the training pairs (the model's own numbering)."""
    groups: torch.Tensor | None = None
    """long ``[P]``: a group key per pair (batches come in runs of ``pairs_per_cell`` of one group), or None."""


class LSCMModel(abc.ABC):
    """Base class of all channel models.

    Subclasses set :attr:`name` (the registry key) and implement :meth:`build`, :meth:`aps`,
    :meth:`state_dict_for_checkpoint` and :meth:`from_checkpoint`, and either :meth:`fit` (closed
    form) or the the trainer's ``Trainable`` protocol methods (iterative).
    """

    name: ClassVar[str]
    supports_unseen_grids: ClassVar[bool] = True

    def __init__(self, angle_grid: AngleGrid, device: torch.device | str = "cpu") -> None:
        self.angle_grid = angle_grid
        self.device = torch.device(device)
        self.fingerprint: str | None = None
        """Fingerprint of the *full* scenario the model was trained for (set by the trainer)."""
        self.run_info: dict[str, Any] = {}
        """Plain-data facts about the run kept in the checkpoint: protocol and split, timings."""

    # --- learning ---------------------------------------------------------------------------
    @classmethod
    @abc.abstractmethod
    def build(cls, config: str | Path | dict[str, Any] | None, angle_grid: AngleGrid, device: torch.device | str) -> LSCMModel:
        """A fresh model from a preset name (``"quick"``/``"full"``), a YAML path, a mapping or ``None`` (defaults)."""

    def fit(
        self,
        scenario: Scenario,
        progress: bool = True,
        callback: Callable[[dict[str, float]], None] | None = None,
        checkpoint_path: str | Path | None = None,
        resume: bool = False,
    ) -> dict[str, float]:
        """Closed-form learning from the round-1 measurements of ``scenario`` (WNOMP overrides it).

        Callers use the trainer's ``fit`` (package ``train``), which trains iterative models (RF-LSCM, NeRF²-LSCM:
        the trainer's ``Trainable`` protocol) step by step and calls this method for the others.
        Protocols (hold-outs, frequency subsets) hand in a scenario whose measurement table is
        already filtered, so a model never needs to know about splits.  Returns a summary
        (e.g. ``{"train_time_s": …}``).
        """
        raise UnsupportedError(f"{self.name} is trained iteratively: use fit(model, scenario) from the train package.")

    @abc.abstractmethod
    def aps(self, cell_ids: np.ndarray, grid_ids: np.ndarray, grid_xyz: np.ndarray | None = None) -> torch.Tensor:
        """APS ``[num_pairs, num_bins]`` (linear path gain, float32, on :attr:`device`) of pairs
        ``cell_ids[num_pairs]`` × ``grid_ids[num_pairs]``.  ``grid_xyz [num_pairs, 3]`` gives the grid
        positions for grids the model has not seen (field models need them).
        Raises :class:`UnsupportedError` where the model has no answer."""

    # --- prediction, shared --------------------------------------------------------------------
    def predict_rsrp(
        self, scenario: Scenario, round: int, beam_type: str, pairs: pd.DataFrame, chunk: int = 4096
    ) -> np.ndarray:
        """Predicted RSRP [dBm] ``[num_pairs, max_beams]`` (NaN past a cell's codebook size) under the
        antenna configuration of ``round`` for ``pairs`` (columns ``cell_id``, ``grid_id``)."""
        cell_ids = pairs["cell_id"].to_numpy()
        grid_ids = pairs["grid_id"].to_numpy()
        grid_xyz = scenario.grids.set_index("grid_id").loc[grid_ids, ["x", "y", "z"]].to_numpy()
        max_beams = max(scenario.codebook(c, beam_type, round).num_beams for c in np.unique(cell_ids)) if len(pairs) else 0
        out = np.full((len(pairs), max_beams), np.nan)
        for cell in np.unique(cell_ids):
            rows = np.flatnonzero(cell_ids == cell)
            a = scenario.sensing(cell, beam_type, self.angle_grid, round=round, device=self.device)  # [beams, bins]
            for start in range(0, len(rows), chunk):
                sel = rows[start : start + chunk]
                with torch.no_grad():
                    x = self.aps(cell_ids[sel], grid_ids[sel], grid_xyz[sel])  # [pairs, bins]
                    power_mw = (x.to(a.dtype) @ a.T).clamp_min(MIN_POWER_MW)
                out[sel, : a.shape[0]] = 10.0 * np.log10(power_mw.cpu().double().numpy())
        return out

    # --- persistence --------------------------------------------------------------------------
    @abc.abstractmethod
    def state_dict_for_checkpoint(self) -> dict[str, Any]:
        """Everything needed to rebuild the fitted model (config as plain dict, tensors)."""

    @classmethod
    @abc.abstractmethod
    def from_checkpoint(cls, state: dict[str, Any], device: torch.device | str = "cpu") -> LSCMModel:
        """Inverse of :meth:`state_dict_for_checkpoint`."""

    def save(self, path: str | Path) -> Path:
        """Write a single checkpoint file atomically (temp file + rename)."""
        from rflscm import __version__

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        payload = {
            "format": "rflscm-checkpoint/1",
            "rflscm_version": __version__,
            "model": self.name,
            "fingerprint": self.fingerprint,
            "angle_grid": self.angle_grid.to_dict(),
            "run_info": self.run_info,
            "state": self.state_dict_for_checkpoint(),
        }
        tmp = path.with_name(path.name + ".tmp")
        torch.save(payload, tmp)
        tmp.replace(path)
        return path


MODEL_REGISTRY: dict[str, type[LSCMModel]] = {}


def register_model(cls: type[LSCMModel]) -> type[LSCMModel]:
    """Class decorator adding a model to :data:`MODEL_REGISTRY` under ``cls.name``."""
    MODEL_REGISTRY[cls.name] = cls
    return cls


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read a checkpoint file's payload, with clear errors for missing or foreign files."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file not found.")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:
        raise CheckpointError(f"{path}: not a readable rflscm checkpoint ({type(exc).__name__}: {exc}).") from None
    if not isinstance(payload, dict) or payload.get("format") != "rflscm-checkpoint/1":
        raise CheckpointError(f"{path}: not an rflscm checkpoint (no `rflscm-checkpoint/1` header).")
    return payload


def load_model(path: str | Path, scenario: Scenario | None = None, device: torch.device | str = "cpu") -> LSCMModel:
    """Load a checkpoint; with ``scenario``, refuse it unless it was fitted on that scenario's round-1 data."""
    import rflscm.models  # noqa: F401  (fills the registry)

    payload = read_checkpoint(path)
    name = payload["model"]
    if name not in MODEL_REGISTRY:
        raise CheckpointError(f"{path}: unknown model {name!r}; known: {', '.join(sorted(MODEL_REGISTRY))}.")
    if scenario is not None and payload["fingerprint"] != scenario.fingerprint():
        raise CheckpointError(
            f"{path}: this checkpoint was trained on another scenario (fingerprint {str(payload['fingerprint'])[:12]}…, "
            f"scenario {scenario.meta.name!r} has {scenario.fingerprint()[:12]}…); retrain it on this scenario."
        )
    model = MODEL_REGISTRY[name].from_checkpoint(payload["state"], device=device)
    model.angle_grid = AngleGrid.from_dict(payload["angle_grid"])
    model.fingerprint = payload["fingerprint"]
    model.run_info = dict(payload.get("run_info", {}))
    return model
