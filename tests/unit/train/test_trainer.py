"""The generic trainer: parameter-group names, grouped epochs, learning-rate schedule, exact state."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from rflscm.errors import ConfigError
from rflscm.models.rflscm_config import TrainConfig
from rflscm.train import Trainer


class Quadratic:
    """A minimal trainable model: w → 3, b → 0."""

    def __init__(self) -> None:
        self.w = nn.Parameter(torch.zeros(1))
        self.b = nn.Parameter(torch.zeros(1))
        self.step = 0
        self.train_state = None
        self.seen: list[list[int]] = []

    def parameter_groups(self):
        return {"tensors": [self.w], "networks": [self.b]}

    def training_losses(self, pairs: torch.Tensor, position: float):
        self.seen.append(pairs.tolist())
        x = pairs.float()
        return {"total": (((self.w - 3) * x) ** 2).mean() + self.b.square().sum()}

    def validation_mae(self) -> float:
        return float("nan")

    def on_step_begin(self, step: int, position: float) -> bool:
        return False


def test_learning_rate_names_must_match_groups() -> None:
    with pytest.raises(ConfigError, match="parameter groups"):
        Trainer(Quadratic(), TrainConfig(lr={"tensors": 0.1}), torch.arange(4))


def test_grouped_epochs_cover_every_pair_once_in_runs_of_one_group() -> None:
    groups = torch.tensor([0] * 7 + [1] * 5 + [2] * 4)
    cfg = TrainConfig(steps=10, batch_pairs=4, pairs_per_cell=2, val_every=100)
    trainer = Trainer(Quadratic(), cfg, torch.arange(16), groups)
    order = trainer._epoch_order()
    assert sorted(order.tolist()) == list(range(16))
    runs, start = [], 0
    g = groups[order]
    for i in range(1, 17):
        if i == 16 or g[i] != g[i - 1] or i - start == 2:
            runs.append(order[start:i].tolist())
            start = i
    assert all(len(set(groups[r].tolist())) == 1 and len(r) <= 2 for r in runs)
    # ungrouped draws are plain permutations, still deterministic for a seed
    a = Trainer(Quadratic(), TrainConfig(seed=3), torch.arange(16))._epoch_order()
    b = Trainer(Quadratic(), TrainConfig(seed=3), torch.arange(16))._epoch_order()
    assert torch.equal(a, b) and sorted(a.tolist()) == list(range(16))


def test_training_decays_lr_and_state_round_trips() -> None:
    cfg = TrainConfig(
        steps=200, batch_pairs=3, pairs_per_cell=1, lr={"tensors": 0.1, "networks": 0.1}, lr_decay=0.1, val_every=100
    )
    model = Quadratic()
    trainer = Trainer(model, cfg, torch.arange(1, 9))
    summary = trainer.run(progress=False)
    assert summary["steps"] == 200 and abs(model.w.item() - 3.0) < 0.2 and model.step == 200
    assert summary["final_loss"] < 0.1
    assert summary["passes"] == 200 * 3 / 8  # steps × batch / pairs
    assert trainer.lr_factor(0.0) == 1.0 and abs(trainer.lr_factor(1.0) - 0.1) < 1e-12
    assert trainer.optimizer.param_groups[0]["lr"] == 0.1 * 0.1 ** (199 / 200)  # the last step's, today's formula
    state = trainer.state_dict()
    other = Trainer(Quadratic(), cfg, torch.arange(1, 9))
    other.load_state_dict(state)
    assert torch.equal(other.next_batch(), trainer.next_batch())


def test_budget_note_only_for_runs_that_barely_see_their_data() -> None:
    from rflscm.cli.common import budget_note

    assert budget_note({"passes": 1.6}) is not None and "1.6 times" in budget_note({"passes": 1.6})
    assert budget_note({"passes": 8.0}) is None
    assert budget_note({"train_time_s": 3.0}) is None  # models without passes (WNOMP)
