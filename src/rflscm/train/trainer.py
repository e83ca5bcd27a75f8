"""The trainer: drives any :class:`Trainable` model (RF-LSCM, NeRF²-LSCM, …) through its steps.

:func:`fit` is the one entry point that learns a model from a scenario: a :class:`Trainable` model is
trained here, step by step; any other model (WNOMP, closed form) fits itself with ``model.fit``.
The trainer sits above the models (``rflscm.models`` imports nothing from ``rflscm.train``) and
knows nothing about fields, rays or HiTAM; it sees the model through :class:`Trainable` only.

Batches are random permutations of the training pairs (an epoch at a time) drawn from a
dedicated generator, optionally in groups of ``pairs_per_cell`` pairs that share a group key
(e.g. the cell, whose rays the model then computes once for the group); learning rates are a pure
function of the step; so a checkpoint holding parameters, optimizer state, step and generator state
resumes *exactly*.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import torch
from torch import nn

from rflscm.errors import ConfigError
from rflscm.models.base import LSCMModel, TrainingPlan, discard_partial_save, read_checkpoint
from rflscm.models.rflscm_config import TrainConfig

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario


@runtime_checkable
class Trainable(Protocol):
    """What the trainer needs of an iteratively trained model.

    * :meth:`prepare` — fresh weights and training data for a scenario; returns the :class:`TrainingPlan`;
    * :meth:`parameter_groups` — ``{name: parameters}``; learning rates are configured by these names;
    * :meth:`training_losses` — ``{"total": …, …}`` of a batch of pair indices at a step;
    * :meth:`validation_mae` — MAE [dB] on held-aside round-1 beams (NaN when none);
    * :meth:`on_step_begin` — per-step hooks (HiTAM hand-over, upsampling); True when the parameter
      objects changed and the optimizer must be rebuilt;
    * :meth:`resume_from` — load weights and step from a checkpoint payload (refusing a foreign one)
      and return the trainer state saved with it;
    * ``step`` (steps done), ``train_state`` (the trainer state :meth:`save` writes along),
      ``train_config`` and :meth:`decoder_evals` (a work counter for throughput).
    """

    step: int
    train_state: dict[str, Any] | None

    @property
    def train_config(self) -> TrainConfig: ...

    def prepare(self, scenario: Scenario) -> TrainingPlan: ...

    def parameter_groups(self) -> dict[str, list[nn.Parameter]]: ...

    def training_losses(self, pairs: torch.Tensor, step: int) -> dict[str, Any]: ...

    def validation_mae(self) -> float: ...

    def on_step_begin(self, step: int) -> bool: ...

    def resume_from(self, payload: dict[str, Any], path: str | Path) -> dict[str, Any]: ...

    def decoder_evals(self) -> int: ...

    def save(self, path: str | Path) -> Path: ...


def fit(
    model: LSCMModel,
    scenario: Scenario,
    progress: bool = True,
    callback: Callable[[dict[str, float]], None] | None = None,
    checkpoint_path: str | Path | None = None,
    resume: bool = False,
) -> dict[str, float]:
    """Learn ``model`` from the round-1 measurements of ``scenario``; returns a summary.

    A :class:`Trainable` model is trained by a :class:`Trainer` (checkpoints written atomically to
    ``checkpoint_path`` every few steps; with ``resume`` it continues exactly from that file); any
    other model fits itself (:meth:`~rflscm.models.LSCMModel.fit`).  ``callback`` receives periodic
    metrics.  The model's fingerprint, when not set already (a protocol sets the full scenario's),
    becomes ``scenario``'s.
    """
    if model.fingerprint is None:
        model.fingerprint = scenario.fingerprint()
    if not isinstance(model, Trainable):
        return model.fit(scenario, progress=progress, callback=callback, checkpoint_path=checkpoint_path, resume=resume)
    discard_partial_save(checkpoint_path)  # a save killed half-way (kill -9) leaves its temporary file behind
    plan = model.prepare(scenario)
    trainer = Trainer(model, model.train_config, plan.pairs, groups=plan.groups)
    if resume and checkpoint_path is not None and Path(checkpoint_path).is_file():
        trainer.load_state_dict(model.resume_from(read_checkpoint(checkpoint_path), checkpoint_path))
    evals0, time0 = model.decoder_evals(), trainer.elapsed_s
    summary = trainer.run(progress=progress, callback=callback, checkpoint_path=checkpoint_path)
    summary["decoder_evals_per_s"] = (model.decoder_evals() - evals0) / max(trainer.elapsed_s - time0, 1e-9)
    model.run_info["train"] = {k: float(v) for k, v in summary.items()}
    return summary


class Trainer:
    """Adam over named parameter groups, exponential learning-rate decay, periodic validation and checkpoints."""

    def __init__(
        self, model: Trainable, cfg: TrainConfig, train_pairs: torch.Tensor, groups: torch.Tensor | None = None
    ) -> None:
        self.model, self.cfg = model, cfg
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

    def lr_factor(self, step: int) -> float:
        """Learning-rate multiplier at ``step``: decays exponentially to ``lr_decay`` at the last step."""
        return self.cfg.lr_decay ** (step / max(self.cfg.steps, 1))

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
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.step = int(state["step"])
        self.optimizer = self._build_optimizer()
        self.optimizer.load_state_dict(state["optimizer"])
        self.generator.set_state(state["generator"])
        torch.set_rng_state(state["torch_rng"])
        self.perm, self.pos = state["perm"].clone(), int(state["pos"])
        self.last_val_mae = float(state["last_val_mae"])
        self.elapsed_s = float(state.get("elapsed_s", 0.0))

    def save(self, path: str | Path) -> None:
        self.model.train_state = self.state_dict()
        self.model.save(path)

    # --- the loop -------------------------------------------------------------------------------
    def train_step(self) -> dict[str, float]:
        """One optimisation step; returns the loss terms (before the update)."""
        if self.model.on_step_begin(self.step):
            self.optimizer = self._build_optimizer()
        factor = self.lr_factor(self.step)
        for group in self.optimizer.param_groups:
            group["lr"] = self.cfg.lr[group["name"]] * factor
        losses = self.model.training_losses(self.next_batch(), self.step)
        self.optimizer.zero_grad(set_to_none=True)
        losses["total"].backward()
        self.optimizer.step()
        self.step += 1
        self.model.step = self.step
        return {k: float(v.detach()) if isinstance(v, torch.Tensor) else float(v) for k, v in losses.items()}

    def run(
        self,
        progress: bool = True,
        callback: Callable[[dict[str, float]], None] | None = None,
        checkpoint_path: str | Path | None = None,
    ) -> dict[str, float]:
        """Train until ``cfg.steps``; returns a summary."""
        from tqdm.auto import tqdm

        cfg = self.cfg
        desc = f"rflscm train ({self.passes(cfg.steps):.1f} passes over {self.train_pairs.numel()} pairs)"
        bar = tqdm(total=cfg.steps, initial=self.step, disable=not progress, desc=desc, dynamic_ncols=True)
        losses: dict[str, float] = {}
        start = time.perf_counter() - self.elapsed_s
        while self.step < cfg.steps:
            losses = self.train_step()
            if not math.isfinite(losses["total"]):
                raise FloatingPointError(f"training loss became {losses['total']} at step {self.step}.")
            if self.step % cfg.val_every == 0 or self.step == cfg.steps:
                self.last_val_mae = float(self.model.validation_mae())
            self.elapsed_s = time.perf_counter() - start
            metrics = {"step": float(self.step), **losses, "val_mae_db": self.last_val_mae, "time_s": self.elapsed_s}
            if checkpoint_path is not None and (self.step % cfg.checkpoint_every == 0 or self.step == cfg.steps):
                self.save(checkpoint_path)
            val = f"{self.last_val_mae:.2f} dB" if math.isfinite(self.last_val_mae) else "pending"
            bar.set_postfix(loss=f"{losses['total']:.4g}", val_mae=val, refresh=False)
            bar.update(1)
            if callback is not None:
                callback(metrics)
        bar.close()
        return {
            "train_time_s": self.elapsed_s,
            "steps": float(self.step),
            "passes": self.passes(self.step),
            "final_loss": losses.get("total", float("nan")),
            "val_mae_db": self.last_val_mae,
        }
