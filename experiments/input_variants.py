"""The `rflscm` command with a decoder-input or fidelity variant patched in, for 10-minute A/Bs (issue 28).

Usage (from the repository root; every argument after the script goes to `rflscm`; evaluate a checkpoint written
this way with the same script and the same variables, since the variants change the forward pass):

    NO_GRID_FEATURES=1 PYTHONPATH=src python experiments/input_variants.py --threads 1 train SCENARIO --minutes 10 --out A.ckpt
    NO_GRID_FEATURES=1 PYTHONPATH=src python experiments/input_variants.py --threads 1 evaluate A.ckpt SCENARIO --json A.json
    CSI_WEIGHT=2 PYTHONPATH=src python experiments/input_variants.py --threads 1 train SCENARIO --minutes 10 --out B.ckpt
    SECOND_LEG=SCENARIO PYTHONPATH=src python experiments/input_variants.py --threads 1 train SCENARIO --minutes 10 --out C.ckpt

The model's ``loss.fidelity: shape`` is ``PAIR_LEVEL_PER_REPORT=0.25`` made an option (`d521757` made it the
default for one commit, at which the runs of ``LEVEL_KEPT`` and ``LEVEL_NOISE_K`` in DECISIONS were made); either of
those two variables switches a log fidelity to ``shape`` and changes its level.

* ``LEVEL_KEPT=s``: the model's shape fidelity keeps the share s of each pair's mean error (1: the log form).
* ``LEVEL_NOISE_K=K``: the shape fidelity removes the share K / (k + K) of a pair's mean error instead (the part of
  it that k reports with independent errors leave uncertain: few reports, mostly removed; many, mostly kept).
* ``GRID_LEVEL=s``: the level is each *grid's* instead of each pair's: a running mean of the log errors of every
  pair of the grid (all cells, both beam types) that the last batches saw, decayed by ``GRID_DECAY`` a step and kept
  per HiTAM stage; a pair's predictions move by (1 − s) times its grid's. The cells' levels relative to each other at
  a grid stay in the loss (they carry the directions from each cell toward the grid); what UE positions and the
  grid's own shadowing add to every cell alike is mostly profiled out.
* ``LEVEL_RAMP=a,b``: the shape fidelity whose kept share of each pair's mean error starts at 1 (the log form) until
  the share a of the schedule and falls linearly to the shape fidelity's (0.2) at b: the field learns its level (what
  a grid without reports needs) early, and its shape after the pairs' levels late.
* ``SMOOTH_LEVEL=K``: the shape fidelity's level is each pair's mean log error less the report-weighted mean of it
  over the pair and its K nearest training pairs of the same cell (their last visit's, per HiTAM stage): the field
  keeps the spatially smooth part of the levels (what a grid without reports needs) in full and the share
  ``LEVEL_KEPT`` of each pair's own departure from it.
* ``PENALTY_ABS=1`` (with ``--set loss.fidelity=shape``): the shape fidelity's missing-beam penalty on the predictions
  before the pair's level moves them, so the bounds of the beams a pair did not report hold the field's own level.
* ``LEVEL_HEAD=w`` (with ``--set loss.fidelity=shape``): a level head of the field's own, g(cell, grid) in bels, a
  small MLP on the fine stage's feature field at the grid (not differentiated), the grid's position, its distance and
  direction from the cell and a cell embedding; every stage's APS is multiplied by 10^g, and g is regressed (weight
  w) on each training pair's mean log error of the whole prediction, so the level that the shape fidelity keeps out
  of the field's loss is learnt apart from the field's angular shape (what a grid without reports needs).
* ``TYPE_LEVEL=1`` (with ``--set loss.fidelity=shape``): the shape fidelity's level per pair *and beam type*, so the
  CSI-RS reports' level relative to the SSB ones at a pair is profiled out too.
* ``CSI_OFFSET=d``: each cell's CSI-RS predictions in the training loss move by a running mean (decayed by d a step)
  of its pairs' CSI-RS mean log error less their SSB one, not differentiated: a CSI-RS level per cell that the field
  need not learn (after training the cell's CSI-RS level correction is fitted anyway).
* ``NO_GRID_FEATURES=1``: the decoder's 𝓜(p_l) (the feature field at the grid) is fed as zeros.
* ``CSI_WEIGHT=W``: the squared fidelity error of the CSI-RS reports counts W times (the SSB reports once).
* ``PAIR_LEVEL=K``: in every training loss each pair's predictions are first moved by its shrunk mean error in bels
  over its reported beams, b = Σ e / (k + K) (k reports; not differentiated), so the field is fitted to each pair's
  reports after a per-pair level that a prior of weight K holds toward 0: the profile of a MAP fit with a free level
  per pair. K = σ²/τ², the report noise over the spread of the pairs' level errors (the anchors measure 2–9).
  ``PAIR_LEVEL_PER_REPORT=c`` adds c × k to K: a share c / (1 + c) of each pair's mean error stays in the loss
  whatever its report count; with ``PAIR_LEVEL_MAX=1``, K = max(PAIR_LEVEL, c × k) instead of the sum.
* ``SECOND_LEG=SCENARIO``: a 2.5-D building height map of SCENARIO's point cloud (the highest building point per
  2 m cell, closed over 3 × 3 cells to fill the scan's gaps) tells, for each (query, sample) pair, which of 6 points
  on the segment from the sample to the grid (from 3 m off the sample to 95 % of the way) lie more than 0.5 m below
  a roof; the radiance's log-amplitude drops by w × that fraction, w a learned scalar of each decoder (start 1.15,
  10 dB of power for a fully blocked second leg). The rendering's transmittance covers only the antenna-to-sample
  leg; this is a geometric cue for the other one.

DECISIONS, "Decoder inputs, the CSI-RS weight and the second leg" and "Each pair's level profiled out of the training
loss" (issue 28, deliverable 2).
"""

from __future__ import annotations

import os
import sys

import numpy as np
import torch
from scipy import ndimage
from torch import nn

from rflscm.data import load_scenario
from rflscm.models.rflscm import fields as F
from rflscm.models.rflscm import losses as L
from rflscm.models.rflscm import model as M

NO_GRID_FEATURES = os.environ.get("NO_GRID_FEATURES") == "1"
CSI_WEIGHT = float(os.environ.get("CSI_WEIGHT", "1"))
SECOND_LEG = os.environ.get("SECOND_LEG", "")
PAIR_LEVEL = float(os.environ.get("PAIR_LEVEL", "0"))
PAIR_LEVEL_PER_REPORT = float(os.environ.get("PAIR_LEVEL_PER_REPORT", "0"))
PAIR_LEVEL_MAX = os.environ.get("PAIR_LEVEL_MAX") == "1"
LEVEL_KEPT = os.environ.get("LEVEL_KEPT", "")
LEVEL_NOISE_K = float(os.environ.get("LEVEL_NOISE_K", "0"))
GRID_LEVEL = os.environ.get("GRID_LEVEL", "")
TYPE_LEVEL = os.environ.get("TYPE_LEVEL") == "1"
CSI_OFFSET = os.environ.get("CSI_OFFSET", "")
LEVEL_RAMP = os.environ.get("LEVEL_RAMP", "")
SMOOTH_LEVEL = int(os.environ.get("SMOOTH_LEVEL", "0"))
PENALTY_ABS = os.environ.get("PENALTY_ABS") == "1"
LEVEL_HEAD = float(os.environ.get("LEVEL_HEAD", "0"))
LEVEL_HEAD_MAX = 2.0  # bels: the head's level lies within ±20 dB
GRID_DECAY = 0.95  # per step: a grid's ~3.5 pairs come back about every 11 steps in the shipped scenario
RES_M, POINTS, SKIP_M, MARGIN_M, LEG_W0 = 2.0, 6, 3.0, 0.5, 1.15
BUILDING = 6  # ASPRS class

# --- NO_GRID_FEATURES ---------------------------------------------------------------------------------------------
_query_inputs = F.RadianceDecoder._query_inputs


def query_inputs_without_grid(self, rays, queries, grid_features):
    return _query_inputs(self, rays, queries, torch.zeros_like(grid_features))


# --- CSI_WEIGHT -----------------------------------------------------------------------------------------------------
_loss, _lscm_loss, _num_ssb = M.RFLSCM._loss, M.lscm_loss, [0]


def loss_noting_ssb(self, a_sel, x, pairs):
    _num_ssb[0] = int(self._training().num_ssb)
    return _loss(self, a_sel, x, pairs)


def weighted_lscm_loss(pred, rsrp, beam_mask, aps, x_scale, bound, fidelity="log", sparsity_weight=1e-3,
                       penalty_weight=0.5, floor=1e-12):
    out = _lscm_loss(pred, rsrp, beam_mask, aps, x_scale, bound, fidelity, sparsity_weight, penalty_weight, floor)
    observed = beam_mask & ~torch.isnan(rsrp)
    err = torch.log10(pred + floor) - torch.log10(torch.where(observed, rsrp, torch.ones_like(rsrp)))
    csi = torch.where(observed, err.square(), torch.zeros_like(err))[:, _num_ssb[0]:]
    extra = (CSI_WEIGHT - 1.0) * csi.sum() / max(pred.shape[0], 1)
    out["fidelity"] = out["fidelity"] + extra
    out["total"] = out["total"] + extra
    return out


# --- PAIR_LEVEL -----------------------------------------------------------------------------------------------------
def level_free_lscm_loss(pred, rsrp, beam_mask, aps, x_scale, bound, fidelity="log", sparsity_weight=1e-3,
                         penalty_weight=0.5, floor=1e-12):
    with torch.no_grad():
        observed = beam_mask & ~torch.isnan(rsrp)
        err = L.log_errors(pred, rsrp, observed, floor)
        k = observed.sum(1)
        prior = PAIR_LEVEL_PER_REPORT * k
        prior = prior.clamp(min=PAIR_LEVEL) if PAIR_LEVEL_MAX else prior + PAIR_LEVEL
        level = err.sum(1) / (k + prior)  # bels
    return _level_loss(pred * torch.pow(10.0, -level)[:, None], rsrp, beam_mask, aps, x_scale, bound, fidelity,
                       sparsity_weight, penalty_weight, floor)


# --- LEVEL_KEPT, LEVEL_NOISE_K (the model's shape fidelity) ---------------------------------------------------------
def shape_lscm_loss(pred, rsrp, beam_mask, aps, x_scale, bound, fidelity="log", *args, **kwargs):
    return _shape_loss(pred, rsrp, beam_mask, aps, x_scale, bound, "shape" if fidelity == "log" else fidelity, *args,
                       **kwargs)


@torch.no_grad()
def noise_pair_level(pred, rsrp, observed, floor=1e-12):
    err = L.log_errors(pred, rsrp, observed, floor)
    k = observed.sum(1)
    return err.sum(1) / k.clamp(min=1) * LEVEL_NOISE_K / (k + LEVEL_NOISE_K)


# --- LEVEL_RAMP (the shape fidelity after a log-form start) ---------------------------------------------------------
_training_losses = M.RFLSCM.training_losses
_FINAL_KEPT = float(os.environ.get("LEVEL_KEPT") or L.LEVEL_KEPT)


def ramped_training_losses(self, pairs, position):
    """The share of each pair's mean error kept: 1 (the log form) until the schedule's share a, then straight down to
    the shape fidelity's share at b."""
    a, b = (float(v) for v in LEVEL_RAMP.split(","))
    p = position / max(float(self.config.train.steps), 1.0)
    t = min(max((p - a) / max(b - a, 1e-9), 0.0), 1.0)
    L.LEVEL_KEPT = 1.0 + t * (_FINAL_KEPT - 1.0)
    return _training_losses(self, pairs, position)


# --- PENALTY_ABS (with loss.fidelity=shape) -------------------------------------------------------------------------
def absolute_penalty_loss(pred, rsrp, beam_mask, aps, x_scale, bound, fidelity="log", sparsity_weight=1e-3,
                          penalty_weight=0.5, floor=1e-12):
    """The shape fidelity with its missing-beam penalty on the predictions as they are, not moved by the pair's level:
    the reporting rule's bounds then hold the field's own level from above at every pair."""
    out = _pen_loss(pred, rsrp, beam_mask, aps, x_scale, bound, fidelity, sparsity_weight, penalty_weight, floor=floor)
    if fidelity != "shape":
        return out
    pen = _pen_loss(pred, rsrp, beam_mask, aps, x_scale, bound, "log", sparsity_weight, penalty_weight,
                    floor=floor)["penalty"]
    out["total"] = out["total"] + penalty_weight * (pen - out["penalty"])
    out["penalty"] = pen
    return out


# --- SMOOTH_LEVEL (the shape fidelity after each pair's level less its neighbourhood's) ---------------------------
_SMOOTH_STATE: dict = {}


def _batch(self, a_sel, x, pairs):
    """A batch's training data, loss config, predictions A x̃, reports, beam mask and log floor (the model's ``_loss``)."""
    d = self._training().data
    return (d, self.config.loss, torch.einsum("bmk,bk->bm", a_sel, x), d.rsrp[pairs], d.beam_mask[pairs],
            10.0 ** (M.FLOOR_DB / 10.0))


def smooth_level_loss(self, a_sel, x, pairs):
    """The shape fidelity whose profiled level is each pair's mean log error *less* the mean of it over the pair and
    its SMOOTH_LEVEL nearest same-cell training pairs (their last visit's, report-weighted): the field keeps the
    spatially smooth part of the pairs' levels in full and a share LEVEL_KEPT of what is each pair's own."""
    from scipy.spatial import cKDTree

    d, c, pred, rsrp, mask, floor = _batch(self, a_sel, x, pairs)
    with torch.no_grad():
        state = _SMOOTH_STATE.setdefault(id(d), {})
        if "nb" not in state:
            cells = d.cell_index.cpu().numpy()
            xyz = d.grid_xyz.cpu().double().numpy()
            nb = np.zeros((len(cells), SMOOTH_LEVEL + 1), np.int64)
            for cell in np.unique(cells):
                rows = np.flatnonzero(cells == cell)
                k = min(SMOOTH_LEVEL + 1, len(rows))
                j = cKDTree(xyz[rows]).query(xyz[rows], k=k)[1].reshape(len(rows), k)
                nb[rows] = rows[np.pad(j, ((0, 0), (0, SMOOTH_LEVEL + 1 - k)), mode="edge")]
            state["nb"] = torch.as_tensor(nb, device=pred.device)
        observed = mask & ~torch.isnan(rsrp)
        err = L.log_errors(pred, rsrp, observed, floor)
        k = observed.sum(1).to(err.dtype)
        mean = err.sum(1) / k.clamp(min=1)
        sums, counts = state.setdefault(a_sel.shape[-1], (torch.zeros(d.cell_index.numel(), device=pred.device),
                                                          torch.zeros(d.cell_index.numel(), device=pred.device)))
        sums[pairs], counts[pairs] = err.sum(1), k  # each pair's last visit
        nb = state["nb"][pairs]
        local = sums[nb].sum(1) / counts[nb].sum(1).clamp(min=1)
        level = torch.where(k > 0, (1.0 - L.LEVEL_KEPT) * (mean - local), 0.0)  # no reports: no level, as `shape`
    pred = pred * torch.pow(10.0, -level)[:, None]
    return M.lscm_loss(pred, rsrp, mask, x, d.x_scale[pairs], d.bound[pairs], "log", M.SPARSITY,
                       c.missing_penalty, floor=floor)


# --- GRID_LEVEL ------------------------------------------------------------------------------------------------------
_GRID_STATE: dict = {}


def grid_level_loss(self, a_sel, x, pairs):
    d, c, pred, rsrp, mask, floor = _batch(self, a_sel, x, pairs)
    with torch.no_grad():
        state = _GRID_STATE.setdefault(id(d), {})
        if "grid" not in state:
            state["grid"] = torch.as_tensor(np.unique(d.grid_ids, return_inverse=True)[1], device=pred.device)
        grid = state["grid"][pairs]
        observed = mask & ~torch.isnan(rsrp)
        err = L.log_errors(pred, rsrp, observed, floor)
        size = int(state["grid"].max()) + 1
        sums, counts = state.setdefault(a_sel.shape[-1], (torch.zeros(size, device=pred.device),
                                                          torch.zeros(size, device=pred.device)))  # per stage
        sums.mul_(GRID_DECAY).index_add_(0, grid, err.sum(1))
        counts.mul_(GRID_DECAY).index_add_(0, grid, observed.sum(1).to(sums.dtype))
        level = (1.0 - float(GRID_LEVEL)) * sums[grid] / counts[grid].clamp(min=1e-6)
    pred = pred * torch.pow(10.0, -level)[:, None]
    return M.lscm_loss(pred, rsrp, mask, x, d.x_scale[pairs], d.bound[pairs], c.fidelity, M.SPARSITY,
                       c.missing_penalty, floor=floor)


# --- TYPE_LEVEL (with loss.fidelity=shape) ---------------------------------------------------------------------------
def type_level_lscm_loss(pred, rsrp, beam_mask, aps, x_scale, bound, fidelity="log", *args, **kwargs):
    """The shape fidelity with a level per (pair, beam type): SSB and CSI-RS reports each after their own mean."""
    if fidelity == "shape":
        with torch.no_grad():
            observed = beam_mask & ~torch.isnan(rsrp)
            err = L.log_errors(pred, rsrp, observed, kwargs.get("floor", 1e-12))
            ssb = torch.arange(pred.shape[1], device=pred.device) < _num_ssb[0]
            level = torch.zeros_like(pred)
            for part in (ssb, ~ssb):
                on = observed & part[None, :]
                mean = (err * on).sum(1) / on.sum(1).clamp(min=1)
                level = torch.where(part[None, :], (1.0 - L.LEVEL_KEPT) * mean[:, None], level)
        pred = pred * torch.pow(10.0, -level)
        fidelity = "log"
    return _type_loss(pred, rsrp, beam_mask, aps, x_scale, bound, fidelity, *args, **kwargs)


# --- CSI_OFFSET (a running CSI-RS level per cell, not differentiated) -------------------------------------------------
_CSI_STATE: dict = {}


def csi_offset_loss(self, a_sel, x, pairs):
    """Each cell's CSI-RS predictions moved by a running mean (decayed by CSI_OFFSET a step, per HiTAM stage) of its
    pairs' CSI-RS mean log error less their SSB mean log error: the cell's CSI-RS level relative to its SSB one (the
    top-4 selection of noisy CSI-RS reports biases them up) is profiled out of the field's training."""
    train, c = self._training(), self.config.loss
    d, num_ssb = train.data, int(train.num_ssb)
    pred = torch.einsum("bmk,bk->bm", a_sel, x)
    rsrp, mask = d.rsrp[pairs], d.beam_mask[pairs]
    floor = 10.0 ** (M.FLOOR_DB / 10.0)
    cells = d.cell_index[pairs]
    with torch.no_grad():
        observed = mask & ~torch.isnan(rsrp)
        err = L.log_errors(pred, rsrp, observed, floor)
        s_on, c_on = observed[:, :num_ssb], observed[:, num_ssb:]
        both = s_on.any(1) & c_on.any(1)
        diff = err[:, num_ssb:].sum(1) / c_on.sum(1).clamp(min=1) - err[:, :num_ssb].sum(1) / s_on.sum(1).clamp(min=1)
        size = int(d.cell_index.max()) + 1
        sums, counts = _CSI_STATE.setdefault(a_sel.shape[-1], (torch.zeros(size, device=pred.device),
                                                               torch.zeros(size, device=pred.device)))
        sums.mul_(float(CSI_OFFSET)).index_add_(0, cells[both], diff[both])
        counts.mul_(float(CSI_OFFSET)).index_add_(0, cells[both], torch.ones_like(diff[both]))
        offset = sums[cells] / counts[cells].clamp(min=1e-6)
        _CSI_STATE["calls"] = _CSI_STATE.get("calls", 0) + 1
        if _CSI_STATE["calls"] % 500 == 1:
            print(f"[csi offset] call {_CSI_STATE['calls']}: mean {10 * float(offset.mean()):+.2f} dB", file=sys.stderr)
    scale = torch.ones_like(pred)
    scale[:, num_ssb:] = torch.pow(10.0, -offset)[:, None]
    return M.lscm_loss(pred * scale, rsrp, mask, x, d.x_scale[pairs], d.bound[pairs], c.fidelity, M.SPARSITY,
                       c.missing_penalty, floor=floor)


# --- LEVEL_HEAD (a level of the field's own, learnt apart from its angular shape) -----------------------------------
class LevelHead(nn.Module):
    """g(cell, grid) [bels] ``[B]``: a scalar level per pair from the fine stage's feature field at the grid (detached),
    the grid's position, its distance and direction from the cell, and a cell embedding; multiplies the whole APS."""

    def __init__(self, feature_dim: int, cell_xyz: np.ndarray, frame) -> None:
        super().__init__()
        self.register_buffer("cell_xyz", torch.as_tensor(cell_xyz, dtype=torch.float32))
        self.register_buffer("lo", torch.tensor(frame.box_lo, dtype=torch.float32))
        self.register_buffer("hi", torch.tensor(frame.box_hi, dtype=torch.float32))
        self.ref_m = float(frame.reference_distance_m)
        self.embed = nn.Embedding(len(cell_xyz), 8)
        width = feature_dim + F.encoded_dim(3, 3) + 4 + 8
        self.net = nn.Sequential(nn.Linear(width, 64), nn.ReLU(), nn.Linear(64, 64), nn.ReLU(), nn.Linear(64, 1))
        nn.init.zeros_(self.net[-1].weight)
        nn.init.zeros_(self.net[-1].bias)

    def forward(self, fields, cells: torch.Tensor, xyz: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            feat = fields.features(fields.encode(xyz))
        rel = xyz - self.cell_xyz[cells]
        dist = rel.norm(dim=-1, keepdim=True).clamp_min(1.0)
        unit = 2.0 * (xyz - self.lo) / (self.hi - self.lo) - 1.0
        parts = [feat, F.positional_encoding(unit, 3), torch.log(dist / self.ref_m), rel / dist, self.embed(cells)]
        return LEVEL_HEAD_MAX * torch.tanh(self.net(torch.cat(parts, -1)).squeeze(-1) / LEVEL_HEAD_MAX)


def _head_level(stages, cells: torch.Tensor, xyz: torch.Tensor) -> torch.Tensor:
    fine = stages["fine"]
    return fine.level_head(fine.fields, cells, xyz.to(torch.float32))


def build_with_head(self, frame):
    """The stages with a level head each (so that HiTAM's copy of the coarse stage into the fine one matches keys);
    only the fine stage's is used and trained."""
    _build_stages(self, frame)
    for stage in self.stages.values():
        stage.level_head = LevelHead(stage.fields.feature_dim, self.scene.cell_xyz, frame).to(self.device)


def step_keeping_head(self, step, position):
    """HiTAM's warm-up end copies the coarse stage into the fine one; the fine stage's level head is kept."""
    kept = {k: v.clone() for k, v in self.stages["fine"].level_head.state_dict().items()}
    out = _on_step_begin(self, step, position)
    self.stages["fine"].level_head.load_state_dict(kept)
    return out


def power_on_with_level(self, stage, kind, cells, grid_xyz, bins, valid):
    """Every stage's APS times 10^g (g not differentiated here: its own loss trains it)."""
    x = _power_on(self, stage, kind, cells, grid_xyz, bins, valid)
    with torch.no_grad():
        g = _head_level(self.stages, cells, grid_xyz)
    return x * torch.pow(10.0, g)[:, None]


def level_head_loss(self, a_sel, x, pairs):
    """The model's loss, plus the head's: g regressed on each pair's mean log error of the whole prediction (the
    field's APS times 10^g, not differentiated), so the head learns the level the shape fidelity leaves out."""
    out = _head_loss(self, a_sel, x, pairs)
    with torch.no_grad():
        d, _, pred, rsrp, mask, floor = _batch(self, a_sel, x, pairs)
        observed = mask & ~torch.isnan(rsrp)
        err = L.log_errors(pred, rsrp, observed, floor)
        k = observed.sum(1)
    has = k > 0
    g = _head_level(self.stages, d.cell_index[pairs], d.grid_xyz[pairs])
    target = g.detach() - err.sum(1) / k.clamp(min=1)
    level = (g - target).square()[has].mean() if bool(has.any()) else g.sum() * 0.0
    out["total"] = out["total"] + LEVEL_HEAD * level
    out["level_head"] = level.detach()
    return out


# --- SECOND_LEG -----------------------------------------------------------------------------------------------------
HEIGHTS: dict = {}


def build_heights(scenario: str) -> None:
    cloud = load_scenario(scenario).point_cloud
    building = cloud.xyz[cloud.classification == BUILDING]
    lo = building[:, :2].min(0) - 4 * RES_M
    cell = np.floor((building[:, :2] - lo) / RES_M).astype(int)
    shape = cell.max(0) + 5
    top = np.full(shape, -1e4)
    np.maximum.at(top, (cell[:, 0], cell[:, 1]), building[:, 2])
    top = ndimage.grey_erosion(ndimage.grey_dilation(top, size=(3, 3)), size=(3, 3))
    HEIGHTS.update(lo=torch.tensor(lo, dtype=torch.float32), top=torch.tensor(top, dtype=torch.float32).reshape(-1),
                   nx=int(shape[0]), ny=int(shape[1]))
    print(f"[second leg] height map {tuple(int(n) for n in shape)}, {(top > -1e3).mean():.0%} under roofs", file=sys.stderr)


def blocked_fraction(p: torch.Tensor, offset: torch.Tensor, dist: torch.Tensor) -> torch.Tensor:
    """Share ``[J]`` of the segment points from samples ``p [J, 3]`` along ``offset [J, 3]`` below a roof."""
    lo, top, nx, ny = HEIGHTS["lo"].to(p.device), HEIGHTS["top"].to(p.device), HEIGHTS["nx"], HEIGHTS["ny"]
    start = (SKIP_M / dist).clamp(max=0.5)
    out = torch.zeros_like(dist)
    for k in range(POINTS):  # a handful of points per pair, each vectorised over every pair
        q = p + (start + (0.95 - start) * (k / (POINTS - 1)))[:, None] * offset
        ix = ((q[:, 0] - lo[0]) / RES_M).long().clamp(0, nx - 1)
        iy = ((q[:, 1] - lo[1]) / RES_M).long().clamp(0, ny - 1)
        out += (top.index_select(0, ix * ny + iy) > q[:, 2] + MARGIN_M).to(out.dtype)
    return out / POINTS


_init = F.RadianceDecoder.__init__


def init_with_leg(self, *args, **kwargs):
    _init(self, *args, **kwargs)
    self.leg_w = nn.Parameter(torch.tensor(LEG_W0))


def pairs_with_leg(self, part, points, along_m, queries, join_query, join_sample, surface):
    """:meth:`RadianceDecoder._pairs` with the second leg's blockage taken off the log-amplitude."""
    frame = self.frame
    along = along_m.index_select(0, join_sample)
    p = points.index_select(0, join_sample)
    offset = queries.grid_xyz.index_select(0, join_query) - p
    dist = offset.norm(dim=-1).clamp_min(1e-3)
    footprint = (along * part.radius.index_select(0, join_query)).clamp_min(self.step_m)
    miss = torch.log1p(dist / footprint)
    hidden = part.sample.index_select(0, join_sample)
    hidden += part.query.index_select(0, join_query)
    if self.pair_in is not None:
        direction = part.direction.index_select(0, join_query)
        surface_j = None if surface is None else surface.index_select(0, join_sample)
        pair = self._pair_inputs(offset / dist[:, None], dist, along, miss, direction, surface_j)
        if torch.is_grad_enabled():
            hidden += self.pair_in(pair)
        else:
            hidden.addmm_(pair, self.pair_in.weight.T)
    out = self.mlp(hidden.relu_())
    log_wl = part.log_wl.index_select(0, join_query)
    log_spread = log_wl + torch.log(frame.reference_distance_m / (along + dist).clamp_min(self.step_m))
    log_spread = log_spread - self.source_decay * miss
    with torch.no_grad():
        blocked = blocked_fraction(p, offset, dist)
    log_spread = log_spread - self.leg_w * blocked
    return torch.exp(torch.complex(out[:, 0] + self.log_amp0 + log_spread, out[:, 1]))


if NO_GRID_FEATURES:
    F.RadianceDecoder._query_inputs = query_inputs_without_grid
if CSI_WEIGHT != 1.0:
    M.RFLSCM._loss = loss_noting_ssb
    M.lscm_loss = weighted_lscm_loss
if PAIR_LEVEL > 0 or PAIR_LEVEL_PER_REPORT > 0:
    _level_loss = M.lscm_loss  # after CSI_WEIGHT's patch, so the two compose
    M.lscm_loss = level_free_lscm_loss
if LEVEL_KEPT:
    L.LEVEL_KEPT = float(LEVEL_KEPT)
if LEVEL_NOISE_K > 0:
    L.pair_level = noise_pair_level
if PENALTY_ABS:
    _pen_loss = M.lscm_loss
    M.lscm_loss = absolute_penalty_loss
if LEVEL_RAMP:
    M.RFLSCM.training_losses = ramped_training_losses
if LEVEL_KEPT or LEVEL_NOISE_K > 0 or LEVEL_RAMP:
    _shape_loss = M.lscm_loss
    M.lscm_loss = shape_lscm_loss
if GRID_LEVEL:
    M.RFLSCM._loss = grid_level_loss
if SMOOTH_LEVEL:
    M.RFLSCM._loss = smooth_level_loss
if TYPE_LEVEL:
    M.RFLSCM._loss = loss_noting_ssb
    _type_loss = M.lscm_loss
    M.lscm_loss = type_level_lscm_loss
if CSI_OFFSET:
    M.RFLSCM._loss = csi_offset_loss
if LEVEL_HEAD > 0:
    from rflscm.models.rflscm import renderer as R

    _build_stages, _power_on, _head_loss = M.RFLSCM._build_stages, R.APSRenderer.power_on, M.RFLSCM._loss
    M.RFLSCM._build_stages = build_with_head
    _on_step_begin = M.RFLSCM.on_step_begin
    M.RFLSCM.on_step_begin = step_keeping_head
    R.APSRenderer.power_on = power_on_with_level
    M.RFLSCM._loss = level_head_loss
if SECOND_LEG:
    build_heights(SECOND_LEG)
    F.RadianceDecoder.__init__ = init_with_leg
    F.RadianceDecoder._pairs = pairs_with_leg

if __name__ == "__main__":
    from rflscm.cli import main

    sys.argv[0] = "rflscm"
    main()
