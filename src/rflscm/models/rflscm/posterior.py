"""The pair posterior: each training pair's APS refined on its own round-1 reports (no parameters).

A field fitted for a few minutes is a good *prior* for a pair's APS (where the power comes from, how
a changed antenna sees it) long before it fits every pair's reports.  The reports of a training pair
are noisy linear measurements of that pair's APS (r = A x, in dB), so the pair's posterior APS is
one small regularised fit away: per-bin gains ``g = 10^(v/10)`` on the field's strongest bins that
bring ``A (x ⊙ g)`` closest to the reports in dB, with a ridge ``λ ‖v‖²`` that keeps the field's
shape where the reports say nothing (a MAP estimate under a log-normal prior centred on the field).
WNOMP fits the same reports with sparse atoms from nothing; here the field supplies the atoms and
their prior weights, and a changed antenna (round 2) reads the refined APS through its own A′.

The fit is Gauss–Newton in the dual: per pair and iteration one ``M × M`` solve over the pair's
``M`` beams (reports not used carry no row).  λ is chosen per fit by holding aside a share of the
reported beams (:func:`held_errors`), per group of pairs with about as many reports; λ = ∞ (no
posterior) is always a candidate, so a posterior that does not predict held-aside beams better than
the field is not applied.  Pairs the training
data never reported (unseen grids, other carriers) keep the field's APS.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import torch

from rflscm.data.pair_lookup import PairLookup
from rflscm.errors import CheckpointError

POSTERIOR_BINS = 256
"""Bins per pair the posterior may re-weight: the strongest of the rendered APS (HiTAM's β² K_C refined
bins fit whole at the presets' sizes)."""
LAMBDAS = (0.1, 0.3, 1.0, 3.0)
"""Candidate ridge weights [1/dB² per dB² of report error]; λ = ∞ (off) is always a candidate too."""
ITERATIONS = 6
"""Gauss–Newton iterations per fit (the fit of a 3-minute field settles by 6: DECISIONS, "The pair posterior")."""
HOLDOUT = 0.2
"""Share of the reports held aside to choose λ."""
LAMBDA_PAIRS = 512
"""λ is chosen on this many training pairs (spread over the pairs' order, which groups them by cell)."""
MAX_GAIN_DB = 30.0
"""A bin's gain is kept within ±30 dB (the reports of one pair cannot justify more)."""
WNOMP_ATOMS = (2, 4)
"""Atoms per pair WNOMP may add to the posterior's candidate bins (``corrections.wnomp_atoms``), chosen with λ on
held-aside reports among these and none."""
WNOMP_TOLERANCE = 0.01
"""WNOMP keeps an atom that lowers its weighted residual by this share (the WNOMP model's default)."""
WNOMP_PRIORS = ((10.0, 0.0), (3.0, 3.0))
"""The prior with WNOMP's atoms, one of these chosen with λ and the atoms on held-aside reports: (how far below
WNOMP's power an atom is centred, how far below its own the field is) [dB].  (10, 0): the field, and WNOMP's atoms
10 dB down where the field has less there (a pair needs the evidence of many reports, the ridge's λ v², to raise
one to WNOMP's fit); (3, 3): about the average of the field's APS and WNOMP's (needs the pair anchors, which carry
the field's share)."""
_DB = 10.0 / math.log(10.0)


def fit_gains(
    cols: torch.Tensor,
    x: torch.Tensor,
    rest: torch.Tensor,
    resid_db: torch.Tensor,
    mask: torch.Tensor,
    lam: float | torch.Tensor,
    iterations: int = ITERATIONS,
) -> torch.Tensor:
    """Per-bin gains [dB] ``v [B, n]`` minimising Σ_m∈mask (e_m(v))² + λ ‖v‖² per pair.

    Args:
        cols: sensing columns ``[B, M, n]`` of each pair's re-weighted bins (any linear power unit).
        x: the field's APS at those bins ``[B, n]`` (same unit as ``cols``' products with it).
        rest: ``A x`` over the pair's other bins ``[B, M]`` (kept as they are).
        resid_db: measured − predicted [dB] at v = 0 ``[B, M]`` (any value where not ``mask``).
        mask: ``[B, M]`` the reports to fit.
        lam: ridge weight λ > 0, one for all pairs or one per pair ``[B]``.
    """
    num_beams = cols.shape[1]
    mask_f = mask.to(cols.dtype)
    resid = torch.where(mask, resid_db, torch.zeros((), dtype=resid_db.dtype, device=resid_db.device))
    f0 = (torch.einsum("bmn,bn->bm", cols, x) + rest).clamp_min(1e-30)
    eye = torch.eye(num_beams, dtype=cols.dtype, device=cols.device)
    eye = lam.to(cols.dtype)[:, None, None] * eye if isinstance(lam, torch.Tensor) else lam * eye
    pair_mask = mask_f[:, :, None] * mask_f[:, None, :]
    v = torch.zeros_like(x)
    # the Jacobian d(dB_m)/d(v_n) is S = diag(1/f) cols diag(w), never formed: S Sᵀ, S v and Sᵀ z go through cols
    for _ in range(iterations):
        w = x * torch.exp(v / _DB)
        f = (torch.einsum("bmn,bn->bm", cols, w) + rest).clamp_min(1e-30)
        e = (resid - 10.0 * torch.log10(f / f0)) * mask_f
        scaled = cols * w[:, None, :]  # [B, M, n]
        gram = scaled @ scaled.transpose(1, 2) / (f[:, :, None] * f[:, None, :])
        rhs = e + torch.einsum("bmn,bn->bm", cols, w * v) / f * mask_f
        z = torch.linalg.solve(gram * pair_mask + eye, rhs[..., None])[..., 0]
        v = (w * torch.einsum("bmn,bm->bn", cols, z * mask_f / f)).clamp(-MAX_GAIN_DB, MAX_GAIN_DB)
    return v


def predicted_change_db(cols: torch.Tensor, x: torch.Tensor, rest: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """How much gains ``v [B, n]`` move each beam's prediction [dB] ``[B, M]``."""
    f0 = (torch.einsum("bmn,bn->bm", cols, x) + rest).clamp_min(1e-30)
    f = (torch.einsum("bmn,bn->bm", cols, x * torch.exp(v / _DB)) + rest).clamp_min(1e-30)
    return 10.0 * torch.log10(f / f0)


def wnomp_atoms(
    matrix: Callable[[int], torch.Tensor],
    cells: torch.Tensor,
    rsrp: torch.Tensor,
    mask: torch.Tensor,
    k_max: int | torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """WNOMP's support of each pair's reports: bins ``[B, K]`` (−1: none) and path gains ``[B, K]``.

    Args:
        matrix: cell index → its sensing matrix ``[M, N]``, the columns the model predicts its reports with.
        cells: each pair's cell index ``[B]``.
        rsrp: the reports ``[B, M]`` in the unit of the matrix times the APS (linear).
        mask: ``[B, M]`` the reports WNOMP may read (the others are left out of its fit).
        k_max: atoms per pair at most, one for all pairs or one per pair ``[B]`` (0: none); ``K`` is the largest.
    """
    from rflscm.models.wnomp_solver import wnomp_solve

    per_pair = torch.as_tensor(k_max, dtype=torch.long).expand(rsrp.shape[0]).to(rsrp.device)
    width = int(per_pair.max()) if per_pair.numel() else 0
    bins = torch.full((rsrp.shape[0], width), -1, dtype=torch.long, device=rsrp.device)
    gains = torch.zeros(rsrp.shape[0], width, dtype=rsrp.dtype, device=rsrp.device)
    r = torch.where(mask, rsrp, torch.full_like(rsrp, math.nan))
    for cell in cells.unique().tolist():  # one solve per cell and atom count: its pairs share the matrix
        a = None
        for k in per_pair[cells == cell].unique().tolist():
            rows = torch.nonzero((cells == cell) & (per_pair == k)).squeeze(1)
            if k <= 0:
                continue
            a = matrix(int(cell)) if a is None else a
            idx, val = wnomp_solve(a, r[rows], k_max=int(k), tolerance=WNOMP_TOLERANCE)
            bins[rows, :k], gains[rows, :k] = idx, val.to(rsrp.dtype)
    return bins, gains


def with_atoms(
    bins: torch.Tensor, x: torch.Tensor, atom_bins: torch.Tensor, atom_x: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The candidate bins of the posterior with atoms added: ``(bins [B, n + k], x [B, n + k], base [B, n + k])``.

    ``bins [B, n]`` and ``x [B, n]`` are the field's bins and APS there, ``atom_bins [B, k]`` (−1: none) and
    ``atom_x [B, k]`` each atom's prior centre.  Each candidate's prior centre is ``x + base``: the field's value,
    raised to the atom's where an atom has more (``base`` ≥ 0 is what is added).  An atom on one of the field's
    bins raises that bin and leaves its own column empty (bin repeated, centre 0: its gain stays 0)."""
    n = bins.shape[1]
    hit = atom_bins[:, :, None] == bins[:, None, :]  # [B, k, n]
    on_field = hit.any(2)
    raise_to = torch.where(hit, atom_x[:, :, None], torch.zeros_like(x[:, None, :])).amax(1)  # [B, n]
    base = torch.cat([(raise_to - x).clamp_min(0.0), torch.where(on_field | (atom_bins < 0), 0.0, atom_x)], 1)
    out_bins = torch.cat([bins, torch.where(on_field | (atom_bins < 0), bins[:, :1], atom_bins)], 1)
    out_x = torch.cat([x, torch.zeros_like(atom_x)], 1)
    assert out_bins.shape[1] == n + atom_bins.shape[1]
    return out_bins, out_x, base


def held_errors(
    cols: torch.Tensor,
    x: torch.Tensor,
    rest: torch.Tensor,
    resid_db: torch.Tensor,
    mask: torch.Tensor,
    held: torch.Tensor,
    lambdas: tuple[float, ...] = LAMBDAS,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per pair, the held-aside absolute errors ``[1 + L, B]`` [dB, summed over the pair's ``mask & held``
    reports] of no posterior (row 0) and of the gains fitted on ``mask & ~held`` with each of ``lambdas``, and how
    many reports each pair held aside ``[B]``."""
    score = mask & held
    rows = [torch.where(score, resid_db.abs(), 0.0).sum(1)]
    for lam in lambdas:
        v = fit_gains(cols, x, rest, resid_db, mask & ~held, lam)
        err = resid_db - predicted_change_db(cols, x, rest, v)
        rows.append(torch.where(score, err.abs(), 0.0).sum(1))
    return torch.stack(rows).double(), score.sum(1)


def report_groups(counts: torch.Tensor, groups: int) -> torch.Tensor:
    """Edges ``[≤ groups − 1]`` (report counts, ascending) that split pairs with ``counts`` reports into up to
    ``groups`` groups of about equal size (fewer where many pairs report the same number); a pair's group is the
    number of edges at or below its count (:func:`group_of`)."""
    if groups <= 1 or not counts.numel():
        return torch.zeros(0, dtype=torch.long)
    q = torch.quantile(counts.double().cpu(), torch.arange(1, groups, dtype=torch.float64) / groups)
    edges = q.ceil().long().unique()
    return edges[edges > int(counts.min())]


def group_of(counts: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    """Each pair's group ``[B]`` given its report ``counts [B]`` and the :func:`report_groups` ``edges``."""
    return (counts.long()[:, None] >= edges.to(counts.device)[None, :]).sum(1)


def pair_rows(state: dict[str, object], values: str, damaged: str) -> tuple[torch.Tensor, ...]:
    """``(cell ids [P], grid ids [P], bins [P, K], state[values] [P, K])`` of a checkpointed per-pair table (the
    posterior's, the left-over pairs'); a table that is not numeric or whose columns' shapes differ is refused in
    one line (:class:`CheckpointError`, ``damaged`` says whose)."""
    try:
        cells = torch.as_tensor(state["cell_id"]).long().reshape(-1)
        grids = torch.as_tensor(state["grid_id"]).long().reshape(-1)
        bins = torch.as_tensor(state["bins"]).long()
        value = torch.as_tensor(state[values]).float()
    except (TypeError, ValueError, RuntimeError):
        raise CheckpointError(f"{damaged} (not numeric); retrain the model.") from None
    if bins.dim() != 2 or bins.shape != value.shape or not len(cells) == len(grids) == bins.shape[0]:
        raise CheckpointError(f"{damaged} (columns of different shapes); retrain the model.")
    return cells, grids, bins, value


@dataclass
class PairPosterior:
    """Per-pair bin gains of the training pairs: ``bins [P, n]`` (fine bin ids) and ``gain_db [P, n]``,
    row ``i`` belonging to pair ``index[i]`` = (cell_id, grid_id); ``lam`` is the chosen λ and ``scores`` the
    held-aside MAE [dB] of every candidate; ``base [P, n]`` (with WNOMP's atoms, else None) is the APS (in the unit
    :meth:`apply` sees) added at each bin before its gain: an atom where the field has less; ``atom_scores`` the
    least held-aside MAE [dB] over λ for each number of WNOMP atoms the choice considered (empty without them).
    ``lam`` and ``scores`` are those of one choice over all pairs; what each group of pairs with about as many
    reports chose (and applies) is in ``groups`` (per group: its least report count, pairs, atoms, centre [dB], λ
    and held-aside MAE [dB])."""

    index: pd.MultiIndex
    bins: torch.Tensor
    gain_db: torch.Tensor
    lam: float
    scores: dict[float, float]
    base: torch.Tensor | None = None
    atom_scores: dict[int, float] = field(default_factory=dict)
    groups: list[dict[str, float]] = field(default_factory=list)

    def apply(self, aps: torch.Tensor, cell_ids: np.ndarray, grid_ids: np.ndarray, owned: bool = False) -> torch.Tensor:
        """``aps [N, K]`` of pairs (``cell_ids``, ``grid_ids`` [N]) with each training pair's gains applied; in place
        where the caller ``owned`` ``aps``, else on a copy."""
        if not len(self.index) or not len(aps):
            return aps
        at = PairLookup.kept_by(self, self.index).rows(cell_ids, grid_ids)
        rows = np.flatnonzero(at >= 0)
        if not rows.size:
            return aps
        src = torch.as_tensor(at[rows], dtype=torch.long)
        gain_db = torch.zeros(rows.size, aps.shape[1], dtype=aps.dtype, device=aps.device)
        bins = self.bins[src].to(aps.device)
        gain_db.scatter_add_(1, bins, self.gain_db[src].to(aps.device, aps.dtype))
        out = aps if owned else aps.clone()
        dst = torch.as_tensor(rows, dtype=torch.long, device=aps.device)
        before = aps[dst]
        if self.base is not None:
            before = before.scatter_add(1, bins, self.base[src].to(aps.device, aps.dtype))
        out[dst] = before * torch.pow(10.0, gain_db / 10.0)
        return out

    def to_state(self) -> dict[str, object]:
        return {
            "cell_id": torch.as_tensor(self.index.get_level_values("cell_id").to_numpy(np.int64, copy=True)),
            "grid_id": torch.as_tensor(self.index.get_level_values("grid_id").to_numpy(np.int64, copy=True)),
            "bins": self.bins.to(torch.int32).cpu().clone(),
            "gain_db": self.gain_db.to(torch.float16).cpu().clone(),
            "lam": float(self.lam),
            "scores": {str(k): float(v) for k, v in self.scores.items()},
            "base": self.base.float().cpu().clone() if self.base is not None else None,
            "atom_scores": {str(k): float(v) for k, v in self.atom_scores.items()},
            "groups": [{str(k): float(v) for k, v in g.items()} for g in self.groups],
        }

    @classmethod
    def from_state(cls, state: dict[str, object] | None, num_bins: int) -> PairPosterior | None:
        """Inverse of :meth:`to_state`; refuses damaged data in one line (:class:`CheckpointError`)."""
        if state is None:
            return None
        damaged = "the checkpoint's pair posterior is damaged"
        keys = ("cell_id", "grid_id", "bins", "gain_db", "lam")
        if not isinstance(state, dict) or any(k not in state for k in keys):
            raise CheckpointError(f"{damaged} (expected {', '.join(keys)}); retrain the model.")
        cells, grids, bins, gain = pair_rows(state, "gain_db", damaged)
        try:
            lam = float(state["lam"])  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise CheckpointError(f"{damaged} (not numeric); retrain the model.") from None
        if not bool(torch.isfinite(gain).all()) or (
            bins.numel() and (int(bins.min()) < 0 or int(bins.max()) >= num_bins)
        ):
            raise CheckpointError(f"{damaged} (non-finite gains or bins off the angle grid); retrain the model.")
        base = state.get("base")
        if base is not None:
            try:
                base = torch.as_tensor(base).float()
            except (TypeError, ValueError, RuntimeError):
                raise CheckpointError(f"{damaged} (not numeric); retrain the model.") from None
            if base.shape != bins.shape or not bool(torch.isfinite(base).all()) or bool((base < 0).any()):
                raise CheckpointError(f"{damaged} (atoms' APS of another shape, negative or non-finite); retrain.")
        index = pd.MultiIndex.from_arrays([cells.numpy(), grids.numpy()], names=["cell_id", "grid_id"])
        scores = {float(k): float(v) for k, v in dict(state.get("scores") or {}).items()}  # type: ignore[call-overload]
        atom_scores = {int(k): float(v) for k, v in dict(state.get("atom_scores") or {}).items()}  # type: ignore[call-overload]
        try:
            groups = [{str(k): float(v) for k, v in dict(g).items()} for g in list(state.get("groups") or [])]  # type: ignore[call-overload]
        except (TypeError, ValueError):
            raise CheckpointError(f"{damaged} (its groups are not numeric); retrain the model.") from None
        return cls(index, bins, gain, lam, scores, base, atom_scores, groups)
