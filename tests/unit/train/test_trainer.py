"""The generic trainer: parameter-group names, grouped epochs, learning-rate schedule, exact state."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from rflscm.errors import CheckpointError, ConfigError
from rflscm.models.rflscm.config import TrainConfig
from rflscm.train import Trainer


class Quadratic:
    """A minimal trainable model: w → 3, b → 0."""

    def __init__(self) -> None:
        self.w = nn.Parameter(torch.zeros(1))
        self.b = nn.Parameter(torch.zeros(1))
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
    assert summary["steps"] == 200 and abs(model.w.item() - 3.0) < 0.2 and trainer.step == 200
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


class FakeClock:
    """A clock that moves only when told (seconds)."""

    def __init__(self, now: float = 0.0) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class Timed(Quadratic):
    """A Quadratic whose every step takes ``step_s`` seconds of a fake clock; records what each step saw."""

    def __init__(self, clock: FakeClock, step_s: float) -> None:
        super().__init__()
        self.clock, self.step_s = clock, step_s
        self.trainer: Trainer | None = None
        self.at: list[tuple[float, float, float]] = []  # (clock at the step's start, position, lr of "tensors")

    def training_losses(self, pairs: torch.Tensor, position: float):
        assert self.trainer is not None
        self.at.append((self.clock.now, position, self.trainer.optimizer.param_groups[1]["lr"]))
        self.clock.now += self.step_s
        return super().training_losses(pairs, position)


def budget_trainer(budget_s: float, step_s: float, prep_s: float = 0.0, steps: int = 1000) -> tuple[Timed, Trainer]:
    clock = FakeClock(prep_s)  # the budget's clock started at 0: ``prep_s`` went to data preparation
    model = Timed(clock, step_s)
    cfg = TrainConfig(steps=steps, batch_pairs=3, lr={"tensors": 0.1, "networks": 0.1}, lr_decay=0.1, val_every=100)
    model.trainer = Trainer(model, cfg, torch.arange(1, 9), budget_s=budget_s, clock=clock)
    return model, model.trainer


def test_budget_mode_stops_after_the_first_step_that_ends_past_the_budget() -> None:
    model, trainer = budget_trainer(budget_s=10.0, step_s=3.0, prep_s=1.0)
    summary = trainer.run(progress=False, started=0.0)
    # steps end at 4, 7, 10 s: the third ends at the budget; the nominal 1000 steps do not matter
    assert summary["steps"] == 3.0 and trainer.step == 3 and [t for t, _, _ in model.at] == [1.0, 4.0, 7.0]
    assert summary["train_time_s"] == 10.0 and summary["budget_s"] == 10.0 and summary["stopped_by_budget"] == 1.0
    assert summary["passes"] == 3 * 3 / 8
    _, longer = budget_trainer(budget_s=10.0, step_s=3.5, prep_s=1.0)
    assert longer.run(progress=False, started=0.0)["steps"] == 3.0  # 1 + 3 × 3.5 = 11.5 s: past it, stops too
    _, short = budget_trainer(budget_s=10.0, step_s=2.0, prep_s=1.0)
    assert short.run(progress=False, started=0.0)["steps"] == 5.0  # ends at 3, 5, 7, 9, 11 s


def test_budget_mode_schedule_follows_the_elapsed_fraction() -> None:
    model, trainer = budget_trainer(budget_s=10.0, step_s=3.0, prep_s=1.0, steps=1000)
    trainer.run(progress=False, started=0.0)
    for clock_s, position, lr in model.at:
        assert lr == 0.1 * 0.1 ** (clock_s / 10.0)  # lr_decay ** (elapsed / budget)
        assert position == clock_s / 10.0 * 1000  # the nominal schedule's step at that fraction
    # a step that starts past the budget (preparation took it all) sits at the schedule's end, not beyond
    model, trainer = budget_trainer(budget_s=10.0, step_s=1.0, prep_s=12.0)
    trainer.run(progress=False, started=0.0)
    assert model.at == [(12.0, 1000.0, 0.1 * 0.1)] and trainer.progress() == 1.0


def test_budget_mode_does_at_least_one_step_and_nothing_after_a_finished_resume() -> None:
    _, trainer = budget_trainer(budget_s=5.0, step_s=1.0, prep_s=7.0)  # preparation alone spent the budget
    assert trainer.run(progress=False, started=0.0)["steps"] == 1.0
    state = trainer.state_dict()
    assert state["budget_s"] == 5.0 and state["elapsed_s"] == 8.0
    model, again = budget_trainer(budget_s=5.0, step_s=1.0)
    again.load_state_dict(state)
    assert again.run(progress=False)["steps"] == 1.0 and model.at == []


def test_budget_must_be_positive_and_resume_must_keep_it() -> None:
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="positive number of seconds"):
            budget_trainer(budget_s=bad, step_s=1.0)
    _, trainer = budget_trainer(budget_s=60.0, step_s=1.0)
    trainer.check_budget({"budget_s": 60.0}, "run.ckpt")  # the same budget resumes
    with pytest.raises(
        CheckpointError,
        match=r"run.ckpt: cannot resume: it was trained to a 120 s budget, this run "
        r"asks for a 60 s budget; resume with --minutes 2",
    ):
        trainer.check_budget({"budget_s": 120.0}, "run.ckpt")
    with pytest.raises(CheckpointError, match=r"a step schedule \(no budget\), this run asks for a 60 s budget"):
        trainer.check_budget({}, "run.ckpt")  # a step-mode checkpoint (also one from before budget mode)
    steps = Trainer(Quadratic(), TrainConfig(), torch.arange(4))
    steps.check_budget({}, "run.ckpt")
    with pytest.raises(CheckpointError, match="a 60 s budget, this run asks for a step schedule"):
        steps.check_budget({"budget_s": 60.0}, "run.ckpt")
