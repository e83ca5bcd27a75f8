"""A generic trainer for radiance-field LSCM models (RF-LSCM, NeRF²-LSCM, …).

The trainer knows nothing about fields, rays or HiTAM; it needs a model with

* ``parameter_groups() -> {name: [parameters]}`` — learning rates are configured by these names;
* ``training_losses(pairs: LongTensor[B], step: int) -> {"total": …, …}``;
* ``validation_mae() -> float`` — MAE [dB] on held-aside round-1 beams (NaN when none);
* ``on_step_begin(step) -> bool`` — per-step hooks (HiTAM hand-over, upsampling); True when the
  parameter objects changed and the optimizer must be rebuilt;
* ``save(path)`` and a ``train_state`` attribute that ``save`` writes along;
* a ``step`` attribute, which the trainer keeps equal to the number of steps done.

Batches are random permutations of the training pairs (an epoch at a time) drawn from a
dedicated generator, optionally in groups of ``pairs_per_cell`` pairs that share a group key
(e.g. the cell, whose rays the model then computes once for the group); learning rates are a pure function of the step; so a checkpoint holding
parameters, optimizer state, step and generator state resumes *exactly*.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from rflscm.errors import ConfigError

if TYPE_CHECKING:  # the config lives with the models, which import this module
    from rflscm.models.rflscm_config import TrainConfig


class Trainer:
    """Adam over named parameter groups, exponential learning-rate decay, periodic validation and checkpoints."""

    def __init__(self, model: Any, cfg: TrainConfig, train_pairs: torch.Tensor, groups: torch.Tensor | None = None) -> None:
        self.model, self.cfg = model, cfg
        self.train_pairs = train_pairs.cpu()
        self.groups = groups.cpu() if groups is not None else None
        self.step = 0
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.perm = torch.empty(0, dtype=torch.long)
        self.pos = 0
        self.last_val_mae = float("nan")
        self.elapsed_s = 0.0
        groups = model.parameter_groups()
        if set(cfg.lr) != set(groups):
            raise ConfigError(
                f"`train.lr` names {sorted(cfg.lr)} do not match the model's parameter groups {sorted(groups)}; "
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
