"""The trainer: drives any :class:`Trainable` model (RF-LSCM, NeRF²-LSCM, …) through its steps.

:func:`fit` is the one entry point that learns a model from a scenario: a :class:`Trainable` model is
trained here, step by step; any other model (WNOMP, closed form) fits itself with ``model.fit``.
The trainer sits above the models (``rflscm.models`` imports nothing from ``rflscm.train``) and
knows nothing about fields, rays or HiTAM; it sees the model through :class:`Trainable` only.

Batches are random permutations of the training pairs (an epoch at a time) drawn from a
dedicated generator, optionally in groups of ``pairs_per_cell`` pairs that share a group key
(e.g. the cell, whose rays the model then computes once for the group).

The schedule (learning-rate decay, and through the model HiTAM's warm-up and ramp and the tensor
upsampling) follows a *progress* fraction p ∈ [0, 1]: p = step / ``train.steps`` (step mode), or
p = min(1, elapsed / training time) when :func:`fit` is given a time budget (budget mode).  A budget is a
promise for the whole fit: the training time is the budget less the time kept for the model's pass after
training (``finish_training``), which the model estimates (``finish_seconds``, measured on two chunks, before the
first step and again halfway, ``REPLAN_AT``) and which may take at most ``train.finish_share`` of what the budget
leaves after a caller's later work, but never less than its least (the levels and WNOMP's APS of every pair,
:attr:`PassCost.least_s`, past the budget's end if need be); training keeps at least ``MIN_TRAIN_SHARE`` of the
budget; that pass is then given the time left, to the budget's end.  The learning-rate factor is ``lr_decay ** p``; the model sees the *schedule position*
p · ``train.steps`` (in units of the nominal schedule's steps; exactly the step in step mode), so ``train.steps``
is the length of the nominal schedule in both modes.  In step mode everything is a pure function of the step, so a
checkpoint holding parameters, optimizer state, step and generator state resumes *exactly*; a budget
run resumes from its saved elapsed time (not bit-identical to an uninterrupted one: timing differs).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import torch
from torch import nn

from rflscm.errors import CheckpointError, ConfigError
from rflscm.models.base import FreshPairs, LSCMModel, PassCost, TrainingPlan, discard_partial_save, read_checkpoint
from rflscm.train.config import LoopConfig

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario


@runtime_checkable
class Trainable(Protocol):
    """What the trainer needs of an iteratively trained model.

    * :meth:`prepare` — fresh weights and training data for a scenario; returns the :class:`TrainingPlan`;
    * :meth:`parameter_groups` — ``{name: parameters}``; learning rates are configured by these names;
    * :meth:`training_losses` — ``{"total": …, …}`` of a batch of pair indices at a schedule position;
    * :meth:`validation_mae` — MAE [dB] on held-aside round-1 beams (NaN when none);
    * :meth:`on_step_begin` — per-step hooks (HiTAM hand-over, upsampling) at the step's schedule
      ``position`` (a float in units of ``train.steps``; in step mode exactly the step); True when the
      parameter objects changed and the optimizer must be rebuilt;
    * :meth:`resume_from` — load weights and schedule position from a checkpoint payload (refusing a
      foreign one); the trainer state saved beside them is the trainer's own (``payload["train_state"]``);
    * :meth:`finish_training` — once after the last step (before the final checkpoint): work that only the
      trained weights need (RF-LSCM's level correction and pair corrections; ``progress``: show a bar); in budget
      mode given ``time_left``, the seconds left of the budget, which it must respect;
    * :meth:`finish_seconds` — what :meth:`finish_training` would cost for all of its work (seconds, and seconds per
      rendered pair), measured now;
    * :meth:`save` — the checkpoint, with the trainer state written beside the model's;
    * ``train_config`` (the loop's knobs) and :meth:`decoder_evals` (a work counter for throughput).

    The trainer owns the step count, the optimizer and the schedule; the model sees only the schedule
    ``position`` of each step (:meth:`on_step_begin`).
    """

    @property
    def train_config(self) -> LoopConfig: ...

    def prepare(self, scenario: Scenario) -> TrainingPlan: ...

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]: ...

    def training_losses(self, pairs: torch.Tensor, position: float) -> dict[str, Any]: ...

    def validation_mae(self) -> float: ...

    def on_step_begin(self, step: int, position: float) -> bool: ...

    def resume_from(self, payload: dict[str, Any], path: str | Path) -> None: ...

    def decoder_evals(self) -> int: ...

    def save(self, path: str | Path, train_state: dict[str, Any] | None = None) -> Path: ...

    def finish_training(
        self,
        progress: bool = False,
        time_left: Callable[[], float] | None = None,
        clock: Callable[[], float] = ...,
        render_rest: bool = False,
        extra_left: Callable[[], float] | None = None,
    ) -> None: ...

    def finish_seconds(self, clock: Callable[[], float] = ..., fresh: FreshPairs | None = None) -> PassCost: ...


def fit(
    model: LSCMModel,
    scenario: Scenario,
    progress: bool = True,
    callback: Callable[[dict[str, float]], None] | None = None,
    checkpoint_path: str | Path | None = None,
    resume: bool = False,
    budget_s: float | None = None,
    clock: Callable[[], float] = time.perf_counter,
    started: float | None = None,
    after_pairs: int = 0,
    after_s: float = 0.0,
    after_fresh: FreshPairs | None = None,
) -> dict[str, float]:
    """Learn ``model`` from the round-1 measurements of ``scenario``; returns a summary (a :class:`Trainable`
    model also records it in ``run_info["train"]`` and ``run_info["fit"]``, whose ``train_time_s`` is then the whole
    fit's, and drops ``run_info["interrupted"]`` before its last checkpoint).

    A :class:`Trainable` model is trained by a :class:`Trainer` (checkpoints written atomically to
    ``checkpoint_path`` every few steps; with ``resume`` it continues from that file, exactly in step
    mode); any other model fits itself (:meth:`~rflscm.models.LSCMModel.fit`; ``budget_s`` does not
    apply to it).  ``callback`` receives periodic metrics.  The model's fingerprint, when not set
    already (a protocol sets the full scenario's), becomes ``scenario``'s.

    With ``budget_s`` (seconds of wall time, counted on ``clock`` from ``started``, default the start of this
    call, data preparation included) the whole fit, the pass after training and the last checkpoint included,
    ends within the budget: training stops after the first step that ends at or past its share (the budget less
    the time kept for the pass after training, see the module's docstring), the schedule follows the elapsed
    fraction of that share instead of the step count (``train.steps`` is then only the length of the nominal
    schedule), and the pass after training gets the time left.  A caller with work of its own after the fit inside
    the same budget (the demo's evaluation) names it: ``after_pairs`` pairs it will ask for that have training
    reports (none of them rendered after the fit: the pass keeps the render of each pair it corrects, answers the
    others with its WNOMP fallback or, where the field's level wins, renders and keeps them too), ``after_fresh``
    pairs without any (always rendered), each at the model's cost per pair measured on a chunk of them, and
    ``after_s`` seconds of other work; the fit keeps that time free too (:func:`budget_split`).  Halfway through
    training (``REPLAN_AT``) the budget is dealt again from the pass's cost measured on the weights trained so far.
    """
    started = clock() if started is None else started
    checked_budget(budget_s)  # before minutes of data preparation
    if model.fingerprint is None:
        model.fingerprint = scenario.fingerprint()
    if not isinstance(model, Trainable):
        return model.fit(scenario, progress=progress, callback=callback, checkpoint_path=checkpoint_path, resume=resume)
    discard_partial_save(checkpoint_path)  # a save killed half-way (kill -9) leaves its temporary file behind
    plan = model.prepare(scenario)
    trainer = Trainer(model, model.train_config, plan.pairs, groups=plan.groups, budget_s=budget_s, clock=clock)
    if resume and checkpoint_path is not None and Path(checkpoint_path).is_file():
        payload = read_checkpoint(checkpoint_path)
        model.resume_from(payload, checkpoint_path)
        state = payload.get("train_state")
        if not isinstance(state, dict):
            raise CheckpointError(f"{checkpoint_path}: cannot resume: the checkpoint holds no optimizer state.")
        trainer.check_budget(state, checkpoint_path)
        trainer.load_state_dict(state)
    deal = None
    if budget_s is not None:
        share = model.train_config.finish_share
        fresh = after_fresh if after_fresh is not None and len(after_fresh) else None
        deal = BudgetDeal(budget_s, share, after_s, 0 if fresh is None else len(fresh), render_rest=after_pairs > 0)
        stop_s = deal.stop_s(model.finish_seconds(clock, fresh))
        if not trainer.replanned:  # a resumed run that re-dealt its budget before keeps that deal
            trainer.stop_s = stop_s
        trainer.replan = lambda: deal.stop_s(model.finish_seconds(clock, fresh))
    evals0, time0 = model.decoder_evals(), clock()
    summary = trainer.run(
        progress=progress,
        callback=callback,
        checkpoint_path=checkpoint_path,
        started=started if budget_s is not None else None,
    )
    summary["decoder_evals_per_s"] = (model.decoder_evals() - evals0) / max(clock() - time0, 1e-9)
    finish0 = clock()
    time_left = None
    extra: dict[str, Any] = {}
    if deal is not None and deal.cost is not None:
        saving = SAVE_SAFETY * trainer.save_s if checkpoint_path else 0.0
        # the least pass always runs (WNOMP's APS for the pairs it cannot reach): a budget too small for the data
        # overruns by it rather than leave pairs with an untrained field, and then corrects no pair beyond its least
        budget_end = finish0 + deal.budget_s - deal.fixed_after_s() - trainer.elapsed_s - saving
        end = max(budget_end, finish0 + least_pass_s(deal.cost))
        time_left = lambda: end - clock()  # noqa: E731
        if end > budget_end:
            extra["extra_left"] = lambda: budget_end - clock()
        if deal.render_rest:  # the pairs the pass leaves to the field's level: rendered by the pass, not the caller
            extra["render_rest"] = True
    model.finish_training(progress=progress, time_left=time_left, clock=clock, **extra)
    summary["finish_s"] = clock() - finish0
    if deal is not None and deal.cost is not None and (deal.after_fresh or deal.after_s):
        summary["after_kept_s"] = deal.fixed_after_s()  # what the last deal kept for the caller's work after the fit
    summary.update(model.run_info.get("corrections", {}))  # how many training pairs the pass corrected
    summary["total_s"] = clock() - started
    model.run_info["train"] = {k: float(v) for k, v in summary.items()}
    model.run_info["fit"] = {**model.run_info["train"], "train_time_s": summary["total_s"]}
    model.run_info.pop("interrupted", None)  # the last checkpoint is the finished model's
    if checkpoint_path is not None:
        trainer.save(checkpoint_path)
    return summary


def budget_split(
    cost: PassCost, budget_s: float, share: float, after_s: float = 0.0, after_fresh: int = 0
) -> tuple[float, float]:
    """``(after, kept)`` [s] of a ``budget_s`` fit: the time kept for a caller's work after it and for the pass after
    training, each with ``FINISH_SAFETY``.  The caller renders its ``after_fresh`` pairs (without training reports,
    at :attr:`~rflscm.models.base.PassCost.fresh_pair_s` each) and spends ``after_s`` seconds on other work; it renders no training pair, as the pass keeps the render of each
    pair it corrects and answers the others without one or renders them itself (``render_rest``).  The pass keeps
    ``share`` of what the caller leaves, at least its least (:func:`least_pass_s`) and at most the whole pass."""
    after = FINISH_SAFETY * (after_fresh * cost.fresh_pair_s + after_s)
    return after, min(FINISH_SAFETY * cost.total_s, max(share * (budget_s - after), least_pass_s(cost)))


@dataclass
class BudgetDeal:
    """How a budget run's ``budget_s`` seconds are dealt between training, the pass after it and a caller's later
    work (:func:`budget_split`), from the pass's measured cost; dealt before the first step and again halfway
    (``REPLAN_AT``), each time from a fresh measurement (:attr:`cost`, the latest)."""

    budget_s: float
    share: float
    after_s: float = 0.0
    after_fresh: int = 0
    render_rest: bool = False
    """A caller renders the training pairs the pass leaves (the pass then renders them itself)."""
    cost: PassCost | None = None

    def stop_s(self, cost: PassCost) -> float:
        """The training's share [s] under ``cost`` (kept as :attr:`cost`): the budget less the caller's later work and
        the pass's time, at least ``MIN_TRAIN_SHARE`` of it."""
        self.cost = cost
        after, kept = budget_split(cost, self.budget_s, self.share, self.after_s, self.after_fresh)
        return max(self.budget_s - after - kept, MIN_TRAIN_SHARE * self.budget_s)

    def fixed_after_s(self) -> float:
        """The caller's later work: its fresh pairs' renders and its other seconds."""
        assert self.cost is not None
        return FINISH_SAFETY * (self.after_fresh * self.cost.fresh_pair_s + self.after_s)


def least_pass_s(cost: PassCost) -> float:
    """The least time [s] a budget's fit keeps for its pass after training: ``FINISH_SAFETY`` × the model's least
    pass (the levels and WNOMP's APS of every pair it cannot reach), whatever the budget: where that does not fit, the
    fit runs past the budget's end rather than leave pairs with a barely trained field, which is worse than trivial
    and which a later evaluation must render (docs/DECISIONS.md, "The demo on a 114-cell city")."""
    return FINISH_SAFETY * cost.least_s


MIN_TRAIN_SHARE = 0.2
"""Training keeps at least this share of a budget, however much the pass after it and a caller's later work (the
demo's evaluation) are estimated to need: a scenario too large for its budget then overruns it (the pass is cut to
its least, see :attr:`~rflscm.models.base.PassCost.least_s`) instead of leaving the field one step of training."""
FINISH_SAFETY = 1.2
"""The time kept for the pass after training is this many times the model's estimate (its measurement is of one
chunk, and the pass also takes its residuals and λ choice); ``train.finish_share`` caps it."""
REPLAN_AT = 0.5
"""A budget run deals its budget again when training has spent this share of its time, from the pass's cost measured
on the weights trained so far: a render's cost follows HiTAM's refined directions, which follow the trained coarse
APS (114-cell city, field regime: 3.6 ms a pair measured before the first step, 6.6 ms after training), and whether
the field with its level already predicts held-aside reports better than WNOMP decides which pairs a caller renders
(docs/DECISIONS.md, "The pass keeps its renders")."""
REPLAN_MIN_STEPS = 20
"""The budget is dealt again only once training has taken this many steps (at ``REPLAN_AT`` or later): where loading
and the first measurement took half the training's share, a second measurement after a step or two would only cost its
seconds (222 cells: one step, then a measurement of several seconds)."""
SAVE_SAFETY = 1.5
"""The pass after training leaves this many times the latest checkpoint's writing time for the final checkpoint."""


def checked_budget(budget_s: float | None) -> float | None:
    """``budget_s`` if it is None or a positive finite number of seconds, else a :class:`ConfigError`."""
    if budget_s is not None and not (math.isfinite(budget_s) and budget_s > 0):
        raise ConfigError(f"the training time budget must be a positive number of seconds (got {budget_s}).")
    return budget_s


class Trainer:
    """Adam over named parameter groups, exponential learning-rate decay, periodic validation and checkpoints.

    Step mode (``budget_s`` None) runs ``cfg.steps`` steps.  Budget mode runs until ``stop_s`` seconds of
    ``clock`` have passed (at least one step): the training's share of the budget, ``budget_s`` unless :func:`fit`
    keeps time for the pass after training; the progress p = min(1, elapsed / stop_s) drives the schedule,
    reaching its end (p = 1, position ``cfg.steps``) when the share is spent.
    """

    def __init__(
        self,
        model: Trainable,
        cfg: LoopConfig,
        train_pairs: torch.Tensor,
        groups: torch.Tensor | None = None,
        budget_s: float | None = None,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        self.model, self.cfg = model, cfg
        self.budget_s, self.clock = checked_budget(budget_s), clock
        self.stop_s = budget_s
        """Budget mode: the training's share of the budget [s] (the schedule and the stop follow it)."""
        self.replan: Callable[[], float] | None = None
        """Budget mode: a new :attr:`stop_s`, dealt once when the progress reaches ``REPLAN_AT`` (:func:`fit`'s)."""
        self.replanned = False
        self.rebased = (0.0, 0.0)
        """``(progress, elapsed_s)`` where the schedule was re-dealt: it goes on from there to 1 at the new stop."""
        self.save_s = 0.0
        """Seconds the latest checkpoint took to write."""
        self.train_pairs = train_pairs.cpu()
        self.groups = groups.cpu() if groups is not None else None
        self.step = 0
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.perm = torch.empty(0, dtype=torch.long)
        self.pos = 0
        self.last_val_mae = float("nan")
        self.elapsed_s = 0.0
        named = model.parameter_groups()
        if set(cfg.lr) != set(named):
            raise ConfigError(
                f"`train.lr` names {sorted(cfg.lr)} do not match the model's parameter groups {sorted(named)}; "
                f"give one learning rate per group."
            )
        self.optimizer = self._build_optimizer()

    # --- pieces ---------------------------------------------------------------------------------
    def _build_optimizer(self) -> torch.optim.Adam:
        groups = self.model.parameter_groups()
        return torch.optim.Adam(
            [{"params": params, "lr": self.cfg.lr[name], "name": name} for name, params in sorted(groups.items())]
        )

    def progress(self) -> float:
        """Schedule progress p ∈ [0, 1] of the next step: ``step / steps`` (step mode) or the spent fraction of
        the training's share of the budget, ``min(1, elapsed_s / stop_s)`` (budget mode; once re-dealt at
        ``(p0, e0)``, it goes on linearly from p0 to 1 at the new ``stop_s``, so that it never jumps back)."""
        if self.stop_s is None:
            return self.step / max(self.cfg.steps, 1)
        p0, e0 = self.rebased
        if self.elapsed_s >= self.stop_s:
            return 1.0
        return min(1.0, p0 + (1.0 - p0) * (self.elapsed_s - e0) / max(self.stop_s - e0, 1e-9))

    def position(self) -> float:
        """Schedule position of the next step, p · ``cfg.steps`` in units of the nominal schedule's steps
        (exactly ``float(step)`` in step mode); the model's HiTAM and upsampling follow it."""
        if self.budget_s is None:
            return float(self.step)
        return self.progress() * self.cfg.steps

    def lr_factor(self, progress: float) -> float:
        """Learning-rate multiplier at schedule ``progress`` p: ``lr_decay ** p``, from 1 down to ``lr_decay``."""
        return self.cfg.lr_decay**progress

    def finished(self) -> bool:
        """Step mode: ``cfg.steps`` done; budget mode: the training's share spent (and at least one step done)."""
        if self.stop_s is None:
            return self.step >= self.cfg.steps
        return self.step > 0 and self.elapsed_s >= self.stop_s

    def passes(self, steps: int) -> float:
        """How many times ``steps`` steps show the model each training pair, on average."""
        return steps * min(self.cfg.batch_pairs, self.train_pairs.numel()) / max(self.train_pairs.numel(), 1)

    def next_batch(self) -> torch.Tensor:
        """The next ``batch_pairs`` pair indices (a fresh permutation each epoch)."""
        out, need = [], min(self.cfg.batch_pairs, self.train_pairs.numel())
        while need > 0:
            if self.pos >= self.perm.numel():
                self.perm = self._epoch_order()
                self.pos = 0
            take = self.perm[self.pos : self.pos + need]
            out.append(take)
            self.pos += take.numel()
            need -= take.numel()
        return torch.cat(out)

    def _epoch_order(self) -> torch.Tensor:
        """A random order of the training pairs; with groups, runs of ``pairs_per_cell`` pairs of one group."""
        order = torch.randperm(self.train_pairs.numel(), generator=self.generator)
        size = self.cfg.pairs_per_cell
        if self.groups is None or size <= 1:
            return self.train_pairs[order]
        key = self.groups[order]
        by_group = torch.sort(key, stable=True).indices
        order, key = order[by_group], key[by_group]
        first = torch.ones_like(key, dtype=torch.bool)
        first[1:] = key[1:] != key[:-1]
        pos = torch.arange(key.numel())
        rank = pos - torch.cummax(torch.where(first, pos, torch.zeros_like(pos)), 0).values  # position in group
        _, chunk = torch.unique(key * (key.numel() + 1) + rank // size, return_inverse=True)
        shuffled = torch.randperm(int(chunk.max()) + 1, generator=self.generator)[chunk]
        return self.train_pairs[order[torch.sort(shuffled * size + rank % size, stable=True).indices]]

    def state_dict(self) -> dict[str, Any]:
        return {
            "step": self.step,
            "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(),
            "torch_rng": torch.get_rng_state(),
            "perm": self.perm.clone(),
            "pos": self.pos,
            "last_val_mae": self.last_val_mae,
            "elapsed_s": self.elapsed_s,
            "budget_s": self.budget_s,
            "replanned": self.replanned,
            "stop_s": self.stop_s,
            "rebased": list(self.rebased),
        }

    def check_budget(self, state: dict[str, Any], path: str | Path) -> None:
        """Refuse to resume the trainer ``state`` of ``path`` under another time budget (or mode)."""
        then = state.get("budget_s")
        if then == self.budget_s:
            return

        def mode(budget: float | None) -> str:
            return "a step schedule (no budget)" if budget is None else f"a {budget:g} s budget"

        hint = "without --minutes" if then is None else f"with --minutes {then / 60:g}"
        raise CheckpointError(
            f"{path}: cannot resume: it was trained to {mode(then)}, this run asks for {mode(self.budget_s)}; "
            f"resume {hint}, or train afresh without --resume."
        )

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.step = int(state["step"])
        self.optimizer = self._build_optimizer()
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
        torch.set_rng_state(state["torch_rng"])
        self.perm, self.pos = state["perm"].clone(), int(state["pos"])
        self.last_val_mae = float(state["last_val_mae"])
        self.elapsed_s = float(state.get("elapsed_s", 0.0))
        self.replanned = bool(state.get("replanned", False))
        if self.replanned:  # the budget was re-dealt before the checkpoint: its deal and schedule go on
            self.stop_s = float(state["stop_s"])
            p0, e0 = state["rebased"]
            self.rebased = (float(p0), float(e0))

    def save(self, path: str | Path) -> None:
        begun = self.clock()
        self.model.save(path, train_state=self.state_dict())
        self.save_s = self.clock() - begun

    # --- the loop -------------------------------------------------------------------------------
    def train_step(self) -> dict[str, float]:
        """One optimisation step; returns the loss terms (before the update)."""
        position = self.position()
        if self.model.on_step_begin(self.step, position):
            self.optimizer = self._build_optimizer()
        factor = self.lr_factor(self.progress())
        for group in self.optimizer.param_groups:
            group["lr"] = self.cfg.lr[group["name"]] * factor
        losses = self.model.training_losses(self.next_batch(), position)
        self.optimizer.zero_grad(set_to_none=True)
        losses["total"].backward()
        self.optimizer.step()
        self.step += 1
        return {k: float(v.detach()) if isinstance(v, torch.Tensor) else float(v) for k, v in losses.items()}

    def run(
        self,
        progress: bool = True,
        callback: Callable[[dict[str, float]], None] | None = None,
        checkpoint_path: str | Path | None = None,
        started: float | None = None,
    ) -> dict[str, float]:
        """Train until :meth:`finished`; returns a summary.  ``started`` is the ``clock`` reading the elapsed
        time counts from (default: now; :func:`fit` passes its own start in budget mode)."""
        cfg, budget = self.cfg, self.stop_s
        bar = self._progress_bar(progress)
        losses: dict[str, float] = {}
        start = (self.clock() if started is None else started) - self.elapsed_s
        if budget is not None:
            self.elapsed_s = self.clock() - start
            bar.update(min(self.elapsed_s, budget) - bar.n)
        while not self.finished():
            losses = self.train_step()
            if not math.isfinite(losses["total"]):
                raise FloatingPointError(f"training loss became {losses['total']} at step {self.step}.")
            validated = self.step % cfg.val_every == 0 or (budget is None and self.step == cfg.steps)
            if validated:
                self.last_val_mae = float(self.model.validation_mae())
            self.elapsed_s = self.clock() - start
            if self._redeal_due():
                self._redeal(start, bar)
            last = self.finished()
            if last and not validated:  # budget mode: the budget ran out between validations
                self.last_val_mae = float(self.model.validation_mae())
            metrics = {"step": float(self.step), **losses, "val_mae_db": self.last_val_mae, "time_s": self.elapsed_s}
            if checkpoint_path is not None and (self.step % cfg.checkpoint_every == 0 or last):
                self.save(checkpoint_path)
            val = f"{self.last_val_mae:.2f} dB" if math.isfinite(self.last_val_mae) else "pending"
            bar.set_postfix(loss=f"{losses['total']:.4g}", val_mae=val, refresh=False)
            bar.update(1 if self.stop_s is None else min(self.elapsed_s, self.stop_s) - bar.n)
            if callback is not None:
                callback(metrics)
        bar.close()
        summary = {
            "train_time_s": self.elapsed_s,
            "steps": float(self.step),
            "passes": self.passes(self.step),
            "final_loss": losses.get("total", float("nan")),
            "val_mae_db": self.last_val_mae,
        }
        if self.stop_s is not None and self.budget_s is not None:
            stop = self.stop_s
            summary.update(budget_s=self.budget_s, train_budget_s=stop, stopped_by_budget=float(self.elapsed_s >= stop))
        return summary

    def _redeal_due(self) -> bool:
        """Whether to deal the budget again now: once, at ``REPLAN_AT`` of the progress, after ``REPLAN_MIN_STEPS``
        steps at least (weights barely trained measure as they did before the first step)."""
        if self.replan is None or self.replanned:
            return False
        return self.progress() >= REPLAN_AT and self.step >= REPLAN_MIN_STEPS

    def _redeal(self, start: float, bar: Any) -> None:
        """Deal the budget again (:attr:`replan`): the schedule goes on from where it is to 1 at the new stop."""
        assert self.replan is not None
        at = (self.progress(), self.elapsed_s)
        stop_s = self.replan()
        self.elapsed_s = self.clock() - start
        self.stop_s, self.rebased, self.replanned = stop_s, at, True
        bar.total = stop_s
        bar.refresh()

    def _progress_bar(self, progress: bool) -> Any:
        """Steps of ``cfg.steps`` (step mode) or seconds of the budget (budget mode)."""
        from tqdm.auto import tqdm

        n = self.train_pairs.numel()
        if self.budget_s is None:
            desc = f"rflscm train ({self.passes(self.cfg.steps):.1f} passes over {n} pairs)"
            return tqdm(total=self.cfg.steps, initial=self.step, disable=not progress, desc=desc, dynamic_ncols=True)
        assert self.stop_s is not None
        desc = f"rflscm train ({self.budget_s / 60:g} min budget, {self.stop_s:.0f} s of it training, {n} pairs)"
        fmt = "{l_bar}{bar}| {n:.0f}/{total:.0f} s [{elapsed}<{remaining}{postfix}]"
        return tqdm(total=self.stop_s, disable=not progress, desc=desc, dynamic_ncols=True, bar_format=fmt)
