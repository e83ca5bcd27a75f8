"""The training loop's knobs, as the trainer reads them.

The trainer sits above the models, so it names the knobs it reads here instead of importing a model's config:
any model's ``train`` config section that has these attributes drives the loop (RF-LSCM's and NeRF²'s
``TrainConfig`` in :mod:`rflscm.models.rflscm.config`, which also carries the model's own data knobs
``val_pairs``).  The post-training pair corrections are not the loop's: they have their own ``corrections``
section.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol


class LoopConfig(Protocol):
    """The knobs of :class:`~rflscm.train.trainer.Trainer` (read-only)."""

    @property
    def steps(self) -> int:
        """Steps of the schedule (budget mode: the nominal schedule's length)."""

    @property
    def batch_pairs(self) -> int:
        """(cell, grid) pairs per step."""

    @property
    def pairs_per_cell(self) -> int:
        """Pairs of a batch come in groups of this many grids of one training group (1: independent draws)."""

    @property
    def lr(self) -> Mapping[str, float]:
        """Adam learning rate per parameter group (names from the model's ``parameter_groups``)."""

    @property
    def lr_decay(self) -> float:
        """Learning rates decay exponentially to this fraction at the end of the schedule."""

    @property
    def finish_share(self) -> float:
        """Budget mode: the most of the budget that the model's pass after training may take."""

    @property
    def val_every(self) -> int:
        """Steps between validation MAEs."""

    @property
    def checkpoint_every(self) -> int:
        """Steps between checkpoints."""

    @property
    def seed(self) -> int:
        """Seed of the batch order."""
