"""What evaluation, prediction and the optimiser ask of a model: an :class:`APSSource`.

A fitted model (:class:`~rflscm.models.base.LSCMModel`), the oracle (:mod:`rflscm.eval.oracle`) and an APS
cache (:mod:`rflscm.eval.cache`) all answer the APS of (cell, grid) pairs on an angle grid; nothing downstream
of training needs more (no ``build``, no ``fit``, no checkpoint).  The shared prediction r = A′ x lives here as
free functions over that protocol (:func:`checked_aps`, :func:`predict_rsrp`), so the oracle and the caches
predict exactly like the models without pretending to be one.  :func:`source_sha256` names what a source
answers, the key of the persisted APS caches.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple, Protocol, cast, runtime_checkable

import numpy as np
import pandas as pd
import torch
from tqdm.auto import tqdm

from rflscm.models.base import MIN_POWER_MW, LSCMModel, NonFiniteError, content_hash, to_plain

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario
    from rflscm.geometry import AngleGrid


class RsrpMix(NamedTuple):
    """A second APS whose predictions a source averages with its own in dB (:func:`mixed_db`).

    A pair's prediction of a beam is ``(1 − w) r₁ + w r₂`` [dB]: ``r₁`` from the source's APS (with its
    :meth:`APSSource.level_offset_db`), ``r₂`` = 10 log₁₀(A x₂) from :attr:`aps` (no offset).  RF-LSCM gives its
    posterior's training pairs WNOMP's APS of their reports here: the two err differently, and their average in dB
    beats each (docs/DECISIONS.md, "Kept: the posterior pairs' predictions averaged in dB").
    """

    aps: torch.Tensor
    """``[num_pairs, num_bins]`` the second APS (zero rows where :attr:`weight` is 0)."""
    weight: torch.Tensor
    """``[num_pairs]`` w in [0, 1]; 0: the source's own prediction alone."""


def mixed_db(own_db: torch.Tensor, other_mw: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """``(1 − w) own_db + w 10 log₁₀(other_mw)`` per row ``[N, ...]`` (``weight [N]``; rows with w = 0 unchanged)."""
    w = weight.to(own_db.dtype).reshape(-1, *([1] * (own_db.dim() - 1)))
    other_db = 10.0 * torch.log10(other_mw.to(own_db.dtype).clamp_min(MIN_POWER_MW))
    return torch.where(w > 0, (1.0 - w) * own_db + w * other_db, own_db)


def rsrp_mix_of(source: object, cell_ids: np.ndarray, grid_ids: np.ndarray, beam_type: str) -> RsrpMix | None:
    """``source.rsrp_mix(cell_ids, grid_ids, beam_type)`` (:class:`RsrpMix`) where the source has that optional member,
    else None."""
    mix = getattr(source, "rsrp_mix", None)
    return None if mix is None else cast("RsrpMix | None", mix(cell_ids, grid_ids, beam_type))


@runtime_checkable
class APSSource(Protocol):
    """Anything that answers the APS of (cell, grid) pairs (a fitted model, the oracle, an APS cache).

    Read-only members, so a model's class attributes (``name``, ``supports_unseen_grids``) satisfy them.  One
    optional member: ``rsrp_mix(cell_ids, grid_ids, beam_type) -> RsrpMix | None``, a second APS averaged in dB into
    the pairs' predictions of that beam type (:func:`rsrp_mix_of`; models have it, returning None unless they mix).
    """

    @property
    def name(self) -> str:
        """The model's registry name (``"rflscm"``, ``"wnomp"``, ...) or ``"oracle"``."""
        ...

    @property
    def angle_grid(self) -> AngleGrid:
        """The grid every APS row lives on."""
        ...

    @property
    def device(self) -> torch.device: ...

    @property
    def supports_unseen_grids(self) -> bool:
        """False: only pairs with training data have an APS (WNOMP)."""
        ...

    @property
    def fingerprint(self) -> str | None:
        """Fingerprint of the full scenario the source was fitted for."""
        ...

    @property
    def run_info(self) -> dict[str, Any]:
        """Plain-data facts of the run (protocol, fit summary); evaluation reads ``protocol`` and ``fit``."""
        ...

    def aps(self, cell_ids: np.ndarray, grid_ids: np.ndarray, grid_xyz: np.ndarray | None = None) -> torch.Tensor:
        """APS ``[num_pairs, num_bins]`` (linear path gain) of pairs ``cell_ids`` × ``grid_ids``; ``grid_xyz
        [num_pairs, 3]`` places grids the source has not seen.  :class:`UnsupportedError` where it has no answer."""
        ...

    def level_offset_db(
        self, cell_ids: np.ndarray, beam_type: str, grid_ids: np.ndarray | None = None
    ) -> np.ndarray | None:
        """dB added to each pair's (``cell_ids``, ``grid_ids``) ``beam_type`` prediction on top of A x, or None."""
        ...


def capped_aps(
    source: object, scenario: Scenario, cell_ids: np.ndarray, grid_ids: np.ndarray, x: torch.Tensor
) -> torch.Tensor:
    """``x [N, bins]`` with each row the source caps (``source.round1_caps(cell_ids, grid_ids)`` → ``[N]`` mW, NaN:
    none; an optional member) scaled down so that its strongest SSB beam under ``scenario``'s round-1 antennas is
    at most the cap: RF-LSCM's pairs that round 1 did not report at a grid it visited were below the reporting
    threshold there (docs/DECISIONS.md, "Kept: pairs round 1 did not report")."""
    caps_of = getattr(source, "round1_caps", None)
    caps = None if caps_of is None else caps_of(cell_ids, grid_ids)
    if caps is None or not np.isfinite(caps).any():
        return x
    cell_ids = np.asarray(cell_ids).reshape(-1)
    scale = torch.ones(len(cell_ids), dtype=torch.float64, device=x.device)
    angle_grid = cast("APSSource", source).angle_grid
    for cell in np.unique(cell_ids[np.isfinite(caps)]):
        rows = np.flatnonzero((cell_ids == cell) & np.isfinite(caps))
        a = scenario.sensing(int(cell), "ssb", angle_grid, round=1, device=x.device)  # [beams, bins]
        at = torch.as_tensor(rows, device=x.device)
        best = (x[at].to(a.dtype) @ a.T).amax(1).double().clamp_min(1e-300)
        cap = torch.as_tensor(caps[rows], dtype=torch.float64, device=x.device)
        scale[at] = torch.clamp(cap / best, max=1.0)
    return x * scale.to(x.dtype)[:, None]


def checked_aps(
    source: APSSource,
    cell_ids: np.ndarray,
    grid_ids: np.ndarray,
    grid_xyz: np.ndarray | None = None,
    scenario: Scenario | None = None,
) -> torch.Tensor:
    """``source.aps``, refusing an answer that is not finite and ≥ 0 (never write NaN or drop beams silently); with
    ``scenario``, capped where the source says round 1 could not have reported the pair (:func:`capped_aps`)."""
    x = source.aps(cell_ids, grid_ids, grid_xyz)
    low, high = torch.aminmax(x) if x.numel() else (torch.zeros(()), torch.zeros(()))
    if not (bool(torch.isfinite(high)) and bool(low >= 0)):  # two reductions (NaN fails both); the mask only then
        bad = ~torch.isfinite(x) | (x < 0)
        pair = int(torch.nonzero(bad.any(1))[0, 0])
        raise NonFiniteError(
            f"the {source.name} model answered a non-finite or negative APS for (cell {int(cell_ids[pair])}, grid "
            f"{int(grid_ids[pair])}) ({int(bad.any(1).sum())} of {len(x)} pairs); its checkpoint is damaged or "
            "its training diverged: retrain it with the `train` command."
        )
    return x if scenario is None else capped_aps(source, scenario, cell_ids, grid_ids, x)


PROGRESS_PAIRS = 2000
"""Predictions of at least this many pairs show a progress bar with an ETA (on a terminal)."""


def predict_rsrp(
    source: APSSource, scenario: Scenario, round: int, beam_type: str, pairs: pd.DataFrame, chunk: int = 4096
) -> np.ndarray:
    """Predicted RSRP [dBm] ``[num_pairs, max_beams]`` (NaN past a cell's codebook size) of ``source`` under the
    antenna configuration of ``round`` for ``pairs`` (columns ``cell_id``, ``grid_id``): r = A′ x in dB plus the
    source's level offset (:meth:`LSCMModel.predict_rsrp` calls this)."""
    cell_ids = pairs["cell_id"].to_numpy()
    grid_ids = pairs["grid_id"].to_numpy()
    grid_xyz = scenario.grids.set_index("grid_id").loc[grid_ids, ["x", "y", "z"]].to_numpy()
    max_beams = max(scenario.codebook(c, beam_type, round).num_beams for c in np.unique(cell_ids)) if len(pairs) else 0
    out = np.full((len(pairs), max_beams), np.nan)
    bar = tqdm(
        total=len(pairs),
        desc=f"predicting {beam_type.upper()} RSRP",
        unit="pair",
        leave=False,
        disable=None if len(pairs) >= PROGRESS_PAIRS else True,  # None: on a terminal only
    )
    offset = source.level_offset_db(cell_ids, beam_type, grid_ids)
    if offset is not None:
        offset = np.asarray(offset, np.float64).reshape(-1)
    for cell in np.unique(cell_ids):
        rows = np.flatnonzero(cell_ids == cell)
        a = scenario.sensing(cell, beam_type, source.angle_grid, round=round, device=source.device)  # [beams, bins]
        for start in range(0, len(rows), chunk):
            sel = rows[start : start + chunk]
            with torch.no_grad():
                x = checked_aps(source, cell_ids[sel], grid_ids[sel], grid_xyz[sel], scenario)  # [pairs, bins]
                own = 10.0 * torch.log10((x.to(a.dtype) @ a.T).clamp_min(MIN_POWER_MW).double())
                if offset is not None:  # the offset belongs to the source's own APS, not to a mixed-in one
                    own = own + torch.as_tensor(offset[sel], dtype=own.dtype, device=own.device)[:, None]
                mix = rsrp_mix_of(source, cell_ids[sel], grid_ids[sel], beam_type)
                if mix is not None:
                    own = mixed_db(own, mix.aps.to(a.device, a.dtype) @ a.T, mix.weight.to(a.device))
            out[sel, : a.shape[0]] = own.cpu().numpy()
            bar.update(len(sel))
    bar.close()
    return out


class Predicts:
    """Mixin giving an :class:`APSSource` that is not a model the models' ``checked_aps`` / ``predict_rsrp``."""

    def checked_aps(
        self,
        cell_ids: np.ndarray,
        grid_ids: np.ndarray,
        grid_xyz: np.ndarray | None = None,
        scenario: Scenario | None = None,
    ) -> torch.Tensor:
        return checked_aps(cast("APSSource", self), cell_ids, grid_ids, grid_xyz, scenario)

    def predict_rsrp(
        self, scenario: Scenario, round: int, beam_type: str, pairs: pd.DataFrame, chunk: int = 4096
    ) -> np.ndarray:
        return predict_rsrp(cast("APSSource", self), scenario, round, beam_type, pairs, chunk)


def source_sha256(source: APSSource) -> str:
    """SHA-256 (hex) of what ``source`` answers, the key of a persisted APS cache.

    For a model, the content hash (:func:`rflscm.models.base.content_hash`) of what its checkpoint's payload
    holds that decides an APS: model name, scenario fingerprint, angle grid and the fitted state (a retrained
    model, another checkpoint or another grid gives another key; loading one checkpoint twice gives the same).
    A source that is not a model provides ``content_sha256()`` itself (the oracle: its scenario and grid; a
    cache: the source it wraps).
    """
    own = getattr(source, "content_sha256", None)
    if callable(own):
        return str(own())
    if not isinstance(source, LSCMModel):
        raise TypeError(f"{type(source).__name__} is neither a model nor has a content_sha256()")
    payload = {
        "model": source.name,
        "fingerprint": source.fingerprint,
        "angle_grid": source.angle_grid.to_dict(),
        "state": source.state_dict_for_checkpoint(),
    }
    return content_hash(to_plain(payload))


__all__ = [
    "APSSource",
    "Predicts",
    "RsrpMix",
    "capped_aps",
    "checked_aps",
    "mixed_db",
    "predict_rsrp",
    "rsrp_mix_of",
    "source_sha256",
]
