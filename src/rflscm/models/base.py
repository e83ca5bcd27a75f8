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

Checkpoints (format ``rflscm-checkpoint/2``) are safe to open and checked (issue 14): they hold only
tensors, numbers, text and lists/dicts of them, read with ``torch.load(weights_only=True)`` so a file
never runs code; numpy arrays travel as tensors and any other value as a JSON string (see
:func:`to_plain`); a SHA-256 over the content, written at save, is verified at load; weights that are
not finite are refused, and so is every non-finite APS a model answers (:meth:`LSCMModel.checked_aps`).
"""

from __future__ import annotations

import abc
import hashlib
import json
import pickle
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np
import pandas as pd
import torch

from rflscm.data.safe_io import atomic_write, discard_stale_temps, is_zip_archive
from rflscm.errors import CheckpointError, DataError, RflscmError, UnsupportedError
from rflscm.geometry import AngleGrid

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.models.source import RsrpMix

MIN_POWER_MW = 1e-30  # floor before taking dB of a predicted RSRP
CHECKPOINT_FORMAT = "rflscm-checkpoint/2"
_NDARRAY, _JSON = "__ndarray__", "__json__"

__all__ = [
    "MIN_POWER_MW",
    "MODEL_REGISTRY",
    "LSCMModel",
    "PassCost",
    "TrainingPlan",
    "UnsupportedError",
    "load_model",
    "model_from_payload",
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


@dataclass(frozen=True)
class PassCost:
    """An iteratively trained model's measured cost of its pass after training (the trainer's ``Trainable``
    protocol, ``finish_seconds``): what a time budget keeps for it, and for renders after the fit."""

    total_s: float
    """Seconds the whole pass would take (every training pair)."""
    per_pair_s: float
    """Seconds per rendered pair (the pass's own rate; an evaluation's renders cost about as much)."""
    least_s: float = 0.0
    """Seconds of the least pass a budget must leave: the levels, and WNOMP's APS of every training pair's own
    reports where the pass cannot reach it (the safety net that keeps an under-trained model near WNOMP)."""
    fresh_s: float | None = None
    """Seconds per pair of a caller's pairs without training reports (:class:`FreshPairs`), timed on a chunk of them:
    their render may cost more than a training pair's (the 222-cell city: 9.3 against 3.8 ms a pair).  None: not
    timed, :attr:`per_pair_s` stands in."""

    @property
    def fresh_pair_s(self) -> float:
        """Seconds per pair of the caller's fresh pairs: :attr:`fresh_s` where timed, else :attr:`per_pair_s`."""
        return self.per_pair_s if self.fresh_s is None else self.fresh_s


@dataclass(frozen=True)
class FreshPairs:
    """The (cell, grid) pairs a caller will ask a fitted model for that have no training reports (the demo's
    evaluation of round-2 pairs that round 1 did not report): a budget's fit keeps the time to render them, timed
    on a chunk of them (:attr:`PassCost.fresh_s`)."""

    cell_ids: np.ndarray
    """``[n]`` cell ids."""
    grid_xyz: np.ndarray
    """``[n, 3]`` grid positions [m] (local frame)."""
    calls: np.ndarray | None = None
    """``[n]`` the caller's call per pair: the pairs it will ask for in one :meth:`LSCMModel.aps` call share a key (the
    evaluation asks cell by cell, a beam type at a time), and keys sort by cell.  None: one call of them all."""

    def __post_init__(self) -> None:
        if len(self.cell_ids) != len(self.grid_xyz):
            raise ValueError(f"{len(self.cell_ids)} cells for {len(self.grid_xyz)} grid positions")
        if self.calls is not None and len(self.calls) != len(self.cell_ids):
            raise ValueError(f"{len(self.calls)} call keys for {len(self.cell_ids)} pairs")

    def __len__(self) -> int:
        return len(self.cell_ids)


class NonFiniteError(RflscmError):
    """A model produced NaN or infinite values (damaged checkpoint, diverged training)."""


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
    def build(
        cls, config: str | Path | dict[str, Any] | None, angle_grid: AngleGrid, device: torch.device | str
    ) -> LSCMModel:
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

    # --- prediction, shared (one implementation for models, the oracle and caches: rflscm.models.source) ---
    def checked_aps(
        self,
        cell_ids: np.ndarray,
        grid_ids: np.ndarray,
        grid_xyz: np.ndarray | None = None,
        scenario: Scenario | None = None,
    ) -> torch.Tensor:
        """:meth:`aps`, refusing an answer that is not finite and ≥ 0 (never write NaN or drop beams silently); with
        ``scenario``, capped where round 1 could not have reported a pair (:func:`~rflscm.models.source.capped_aps`)."""
        from rflscm.models.source import checked_aps

        return checked_aps(self, cell_ids, grid_ids, grid_xyz, scenario)

    def predict_rsrp(
        self, scenario: Scenario, round: int, beam_type: str, pairs: pd.DataFrame, chunk: int = 4096
    ) -> np.ndarray:
        """Predicted RSRP [dBm] ``[num_pairs, max_beams]`` (NaN past a cell's codebook size) under the
        antenna configuration of ``round`` for ``pairs`` (columns ``cell_id``, ``grid_id``)."""
        from rflscm.models.source import predict_rsrp

        return predict_rsrp(self, scenario, round, beam_type, pairs, chunk)

    def level_offset_db(
        self, cell_ids: np.ndarray, beam_type: str, grid_ids: np.ndarray | None = None
    ) -> np.ndarray | None:
        """dB added to every ``beam_type`` prediction of each pair (cell ``cell_ids [P]``, grid ``grid_ids [P]``,
        None: every pair of those cells) on top of A x (a level the APS cannot carry because it differs between beam
        types), or None (the default: nothing)."""
        return None

    def rsrp_mix(self, cell_ids: np.ndarray, grid_ids: np.ndarray, beam_type: str) -> RsrpMix | None:
        """A second APS averaged in dB into the pairs' ``beam_type`` predictions
        (:class:`~rflscm.models.source.RsrpMix`), or None (the default: the model's own APS alone)."""
        return None

    def round1_caps(self, cell_ids: np.ndarray, grid_ids: np.ndarray) -> np.ndarray | None:
        """Per pair the most [mW] its strongest round-1 SSB beam may be predicted at (NaN: no cap), or None (the
        default: no caps; :func:`~rflscm.models.source.capped_aps`)."""
        return None

    # --- persistence --------------------------------------------------------------------------
    @abc.abstractmethod
    def state_dict_for_checkpoint(self) -> dict[str, Any]:
        """Everything needed to rebuild the fitted model (config as plain dict, tensors)."""

    @classmethod
    @abc.abstractmethod
    def from_checkpoint(cls, state: dict[str, Any], device: torch.device | str = "cpu") -> LSCMModel:
        """Inverse of :meth:`state_dict_for_checkpoint`."""

    def check_loaded(self) -> None:  # noqa: B027 - an optional hook, not abstract
        """Called by :func:`load_model` after :meth:`from_checkpoint` (and the angle grid) are in place:
        subclasses check that what they read is consistent (index ranges, shapes) and raise
        :class:`CheckpointError` otherwise.  The default checks nothing."""

    def save(self, path: str | Path, train_state: dict[str, Any] | None = None) -> Path:
        """Write a single checkpoint file atomically (temp file, fsync, rename); see the module docstring.
        ``train_state``: the trainer's state (step, optimizer, generators), saved beside the model's."""
        from rflscm import __version__

        path = Path(path)
        if path.is_dir():
            example = path / "model.ckpt"
            raise CheckpointError(f"{path}: is a folder; give the checkpoint a file name (e.g. {example}).")
        path.parent.mkdir(parents=True, exist_ok=True)
        payload = to_plain(
            {
                "rflscm_version": __version__,
                "model": self.name,
                "fingerprint": self.fingerprint,
                "angle_grid": self.angle_grid.to_dict(),
                "run_info": self.run_info,
                "state": self.state_dict_for_checkpoint(),
                "train_state": train_state,
            }
        )
        checkpoint = {"format": CHECKPOINT_FORMAT, "sha256": content_hash(payload), "payload": payload}

        def write(tmp: Path) -> None:
            with open(tmp, "wb") as f:
                torch.save(checkpoint, f)

        atomic_write(path, write, "checkpoint")  # a unique temporary name: concurrent saves never collide
        return path


def partial_save_path(path: str | Path) -> Path:
    """The temporary file :meth:`LSCMModel.save` writes before renaming it to ``path``."""
    path = Path(path)
    return path.with_name(path.name + ".tmp")


def discard_partial_save(path: str | Path | None) -> None:
    """Remove the temporary file of a save that was interrupted (kill -9, full disk) before it was renamed."""
    discard_stale_temps(path)


def to_plain(value: Any) -> Any:
    """``value`` as tensors, numbers, str, None, lists and str/int-keyed dicts only (what
    ``torch.load(weights_only=True)`` reads): a numpy array becomes ``{"__ndarray__": tensor}``, a numpy
    scalar a number, a tuple a list, and anything else ``{"__json__": text}``.  :func:`from_plain` inverts it."""
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, np.ndarray):
        try:
            return {_NDARRAY: torch.from_numpy(np.ascontiguousarray(value).copy())}
        except TypeError:  # text or object arrays, dtypes torch has no tensor for
            return {_JSON: json.dumps(value.tolist(), default=str)}
    if isinstance(value, np.generic):
        return value.item()
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if isinstance(value, dict):
        return {(k if isinstance(k, (str, int)) else str(k)): to_plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_plain(v) for v in value]
    return {_JSON: json.dumps(value, default=str)}


def from_plain(value: Any) -> Any:
    """Inverse of :func:`to_plain` (lists stay lists)."""
    if isinstance(value, dict):
        if len(value) == 1 and _NDARRAY in value:
            return value[_NDARRAY].numpy()
        if len(value) == 1 and _JSON in value:
            return json.loads(value[_JSON])
        return {k: from_plain(v) for k, v in value.items()}
    if isinstance(value, list):
        return [from_plain(v) for v in value]
    return value


MAX_EXPANDED_BYTES = 256 * 2**20
"""A tensor whose shape claims more bytes than its storage holds (stride 0) is refused above this size [bytes]."""


def content_hash(value: Any) -> str:
    """SHA-256 (hex) of a plain value: every key, number, text, and every tensor's dtype, shape and bytes, in a
    fixed order, so it does not depend on how pickle lays the file out."""
    h = hashlib.sha256()
    _hash_into(h, value)
    return h.hexdigest()


def _hash_into(h: Any, value: Any) -> None:
    if isinstance(value, torch.Tensor):
        claimed = value.numel() * value.element_size()
        if claimed > MAX_EXPANDED_BYTES and claimed > value.untyped_storage().nbytes():  # stride 0 in a small file
            raise CheckpointError(
                f"a tensor of shape {tuple(value.shape)} claims {claimed:,} bytes but stores "
                f"{value.untyped_storage().nbytes():,}; refused before expanding it (limit {MAX_EXPANDED_BYTES:,} bytes)."
            )
        t = value.detach().cpu().contiguous()
        h.update(f"T{t.dtype}{tuple(t.shape)}".encode())
        h.update(t.reshape(-1).view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    elif isinstance(value, dict):
        h.update(f"D{len(value)}".encode())
        for key in sorted(value, key=repr):
            h.update(f"K{key!r}".encode())
            _hash_into(h, value[key])
    elif isinstance(value, (list, tuple)):
        h.update(f"L{len(value)}".encode())
        for item in value:
            _hash_into(h, item)
    else:
        h.update(f"V{type(value).__name__}:{value!r}".encode())


def _first_non_finite(value: Any, where: str = "") -> str | None:
    """Key path of the first floating-point tensor holding NaN or ±inf (``None`` when all are finite)."""
    if isinstance(value, torch.Tensor):
        if value.is_floating_point() or value.is_complex():
            return None if bool(torch.isfinite(value).all()) else where
        return None
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, item in items:
        if key == _NDARRAY:
            found = _first_non_finite(item, where)
        else:
            found = _first_non_finite(item, f"{where}.{key}" if where else str(key))
        if found is not None:
            return found
    return None


def require_round1_reports(scenario: Scenario, model_name: str) -> int:
    """Number of reported (non-empty) round-1 RSRP values; none is a :class:`DataError` (every model learns
    from round 1, so fitting on nothing would give a model that answers nothing or noise)."""
    m = scenario.measurements
    round1 = (m["round"] == 1).to_numpy()
    reported = int(np.isfinite(m["rsrp_dbm"].to_numpy(dtype=np.float64)[round1]).sum())
    if reported == 0:
        raise DataError(
            f"scenario {scenario.meta.name!r} has no reported round-1 RSRP ({int(round1.sum())} round-1 rows, all "
            f"empty); {model_name} learns from round 1: add round-1 measurements "
            f"({scenario.meta.measurements or 'none'})."
        )
    return reported


MODEL_REGISTRY: dict[str, type[LSCMModel]] = {}


def register_model(cls: type[LSCMModel]) -> type[LSCMModel]:
    """Class decorator adding a model to :data:`MODEL_REGISTRY` under ``cls.name``."""
    MODEL_REGISTRY[cls.name] = cls
    return cls


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """Read and verify a checkpoint file's payload (``format`` … ``state``, numpy arrays restored).

    Raises:
        CheckpointError: missing file, a folder, unreadable, not an rflscm checkpoint, holds Python objects
            other than plain data (refused unread), its content does not match its SHA-256, or holds
            non-finite weights.
    """
    path = Path(path)
    if path.is_dir():
        raise CheckpointError(f"{path}: is a folder, not a checkpoint file; give the .ckpt file.")
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file not found.")
    try:
        with open(path, "rb") as f:
            f.read(4)
    except OSError as exc:
        raise CheckpointError(f"{path}: cannot read the checkpoint ({exc.strerror or type(exc).__name__}).") from None
    if not is_zip_archive(path):
        raise CheckpointError(
            f"{path}: not an rflscm checkpoint (not a PyTorch archive; damaged, truncated or another kind of file)."
        )
    try:
        archive = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        if "unsupported global" in str(exc).lower() or "unsupported class" in str(exc).lower():
            raise CheckpointError(
                f"{path}: refused: the file holds Python objects other than tensors and plain data, which could run "
                "code when loaded; rflscm checkpoints never do (a file from elsewhere, or from an rflscm before "
                "checkpoint format 2: retrain it with the `train` command)."
            ) from None
        raise CheckpointError(f"{path}: not a readable rflscm checkpoint ({first}).") from None
    except PermissionError:
        raise CheckpointError(f"{path}: cannot read the checkpoint (permission denied).") from None
    except Exception as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(
            f"{path}: not a readable rflscm checkpoint (damaged, truncated or another kind of file: {first[:200]})."
        ) from None
    if not isinstance(archive, dict) or archive.get("format") not in (CHECKPOINT_FORMAT, "rflscm-checkpoint/1"):
        raise CheckpointError(f"{path}: not an rflscm checkpoint (no `{CHECKPOINT_FORMAT}` header).")
    if archive["format"] != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: written by an older rflscm (format 1); retrain it with the `train` command.")
    payload = archive.get("payload")
    try:
        digest = content_hash(payload) if isinstance(payload, dict) else None
    except CheckpointError as exc:
        raise CheckpointError(f"{path}: {exc}") from None
    if not isinstance(payload, dict) or archive.get("sha256") != digest:
        raise CheckpointError(
            f"{path}: the content does not match the SHA-256 written when it was saved (the file is damaged or was "
            "edited); restore it or retrain with the `train` command."
        )
    bad = _first_non_finite(payload.get("state"))
    if bad is not None:
        raise CheckpointError(
            f"{path}: holds non-finite values (NaN or inf) in `{bad}`; training diverged or the file was damaged: "
            "retrain with the `train` command."
        )
    payload = from_plain(payload)
    missing = [k for k in ("model", "fingerprint", "angle_grid", "state") if k not in payload]
    if missing:
        raise CheckpointError(f"{path}: incomplete checkpoint (no {', '.join(missing)}); retrain it.")
    payload["format"] = CHECKPOINT_FORMAT
    return payload


def model_from_payload(payload: dict[str, Any], device: torch.device | str = "cpu") -> LSCMModel:
    """The fitted model a checkpoint payload describes (``model``, ``state``, ``angle_grid``, ``fingerprint``,
    ``run_info``, as :meth:`LSCMModel.save` writes them), checked (:meth:`LSCMModel.check_loaded`); the model's
    name must be registered."""
    import rflscm.models  # noqa: F401  (fills the registry)

    model = MODEL_REGISTRY[str(payload["model"])].from_checkpoint(payload["state"], device=device)
    model.angle_grid = AngleGrid.from_dict(payload["angle_grid"])
    model.fingerprint = payload.get("fingerprint")
    model.run_info = dict(payload.get("run_info") or {})
    model.check_loaded()
    return model


def load_model(path: str | Path, scenario: Scenario | None = None, device: torch.device | str = "cpu") -> LSCMModel:
    """Load a checkpoint; with ``scenario``, refuse it unless it was fitted on that scenario's round-1 data."""
    import rflscm.models  # noqa: F401  (fills the registry)

    payload = read_checkpoint(path)
    name = str(payload["model"])
    if name not in MODEL_REGISTRY:
        raise CheckpointError(f"{path}: unknown model {name!r}; known: {', '.join(sorted(MODEL_REGISTRY))}.")
    if scenario is not None and payload["fingerprint"] != scenario.fingerprint():
        raise CheckpointError(
            f"{path}: this checkpoint was trained on another scenario (fingerprint {str(payload['fingerprint'])[:12]}…, "
            f"scenario {scenario.meta.name!r} has {scenario.fingerprint()[:12]}…); retrain it on this scenario."
        )
    try:  # last-resort guard over reading a file: the hash passed, so this is a consistent but foreign layout
        model = model_from_payload(payload, device)
    except RflscmError as exc:
        raise CheckpointError(f"{path}: {exc}") from None
    except (KeyError, IndexError, TypeError, ValueError, RuntimeError, AttributeError) as exc:
        raise CheckpointError(
            f"{path}: the checkpoint's content does not fit the {name!r} model of this rflscm version "
            f"({type(exc).__name__}: {str(exc).strip().splitlines()[0][:200] if str(exc).strip() else ''}); "
            "retrain it with the `train` command."
        ) from None
    return model
