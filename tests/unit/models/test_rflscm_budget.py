"""RF-LSCM trained to a time budget (fake clock): HiTAM and the hand-over follow the schedule position."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from tiny_rflscm import Interrupt, stop_at, tiny_config

from rflscm.data import load_scenario
from rflscm.data.examples import tiny_scenario
from rflscm.errors import CheckpointError
from rflscm.geometry import AngleGrid
from rflscm.models.base import FreshPairs, PassCost
from rflscm.models.rflscm import RFLSCM
from rflscm.train import fit

GRID = AngleGrid.full_sphere(10, 12)


def fresh_pairs(count: int) -> FreshPairs:
    """``count`` pairs without training reports (cell 0, grids along x)."""
    return FreshPairs(np.zeros(count, np.int64), np.stack([np.arange(count), np.zeros(count), np.ones(count)], 1))


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    return load_scenario(tiny_scenario(tmp_path_factory.mktemp("tiny"), seed=0))


class StepClock:
    """A fake clock that moves ``step_s`` seconds whenever the model begins a training step."""

    def __init__(self, step_s: float) -> None:
        self.now, self.step_s = 0.0, step_s

    def __call__(self) -> float:
        return self.now


def timed_model(clock: StepClock, seen: list[tuple[int, float, bool]]) -> RFLSCM:
    """Tiny RF-LSCM (nominal 8 steps, warm-up 4, ramp 2) whose steps take ``clock.step_s``; records for each step
    (step, position, whether the refinement model was just handed the coarse model's fields)."""
    model = RFLSCM.build(tiny_config(), GRID)
    begin = model.on_step_begin

    def same_fields() -> bool:
        fine, coarse = model.stage("fine").fields.state_dict(), model.stage("coarse").fields.state_dict()
        return all(torch.equal(fine[k], coarse[k]) for k in fine)

    def on_step_begin(step: int, position: float) -> bool:
        clock.now += clock.step_s
        before = same_fields()
        changed = begin(step, position)
        seen.append((step, position, same_fields() and not before))
        return changed

    model.on_step_begin = on_step_begin  # type: ignore[method-assign]
    return model


def test_hand_over_and_alpha_follow_the_position_not_the_step(scenario) -> None:
    clock, seen, metrics = StepClock(10.0), [], []
    model = timed_model(clock, seen)
    summary = fit(model, scenario, progress=False, budget_s=100.0, clock=clock, callback=metrics.append)
    # step k begins at 10 k s of 100: position 0.8 k of the nominal 8 steps; the 10th step ends at the budget
    assert summary["steps"] == 10.0 and summary["stopped_by_budget"] == 1.0
    assert [p for _, p, _ in seen] == [k * 10.0 / 100.0 * 8 for k in range(10)]
    handed = [step for step, _, now in seen if now]
    assert handed == [5]  # position 4.0 crosses warm-up 4 at step 5 (step mode: step 4)
    hitam = model.hitam
    assert hitam is not None
    assert [m["alpha"] for m in metrics] == [hitam.alpha(p) for _, p, _ in seen]
    assert [m["alpha"] for m in metrics][4:7] == pytest.approx([0.0, 0.5, 0.9])  # positions 3.2, 4.0, 4.8
    assert model.position == pytest.approx(7.2)


def test_budget_resume_continues_from_the_saved_time_and_refuses_another_budget(scenario, tmp_path) -> None:
    clock, seen, reference = StepClock(10.0), [], []
    fit(
        timed_model(clock, seen),
        scenario,
        progress=False,
        budget_s=100.0,
        clock=clock,
        callback=lambda m: reference.append(m["total"]),
    )

    ckpt = tmp_path / "run.ckpt"
    clock, seen = StepClock(10.0), []
    with pytest.raises(Interrupt):
        fit(
            timed_model(clock, seen),
            scenario,
            progress=False,
            budget_s=100.0,
            clock=clock,
            callback=stop_at(4),
            checkpoint_path=ckpt,
        )
    clock, seen, resumed = StepClock(10.0), [], []
    fit(
        timed_model(clock, seen),
        scenario,
        progress=False,
        budget_s=100.0,
        clock=clock,
        checkpoint_path=ckpt,
        resume=True,
        callback=lambda m: resumed.append(m["total"]),
    )
    # the fake clock makes the resumed run's times those of the uninterrupted one (a real clock would not)
    assert seen[0][:2] == (4, 3.2) and resumed == reference[4:]
    for budget, text in ((120.0, "a 120 s budget"), (None, "a step schedule")):
        with pytest.raises(CheckpointError, match=f"trained to a 100 s budget, this run asks for {text}"):
            fit(
                RFLSCM.build(tiny_config(), GRID),
                scenario,
                progress=False,
                budget_s=budget,
                checkpoint_path=ckpt,
                resume=True,
            )


def test_a_budget_keeps_time_for_the_pass_after_training_and_gives_it_the_rest(scenario) -> None:
    """The fit ends within the budget: the model's estimate of its pass (capped by ``train.finish_share``) is taken
    off the training, the schedule spans what is left, and the pass is told the seconds left to the budget's end."""
    for share, estimate, stop in ((0.5, 30.0, 64.0), (0.2, 30.0, 80.0), (0.5, 0.0, 100.0)):
        clock, seen, left = StepClock(10.0), [], []
        model = timed_model(clock, seen)
        model.config = dataclasses.replace(
            model.config, train=dataclasses.replace(model.config.train, finish_share=share)
        )
        model.finish_seconds = lambda clock, fresh=None, e=estimate: PassCost(e, 0.5)  # type: ignore[method-assign]
        model.finish_training = lambda progress=False, time_left=None, clock=None, seen=left: seen.append(time_left())  # type: ignore[method-assign]
        summary = fit(model, scenario, progress=False, budget_s=100.0, clock=clock)
        # kept = min(1.2 × estimate, share × budget); steps of 10 s stop at the first end at or past the rest
        steps = math.ceil(stop / 10.0)
        assert summary["steps"] == steps and summary["train_budget_s"] == pytest.approx(stop)
        assert [p for _, p, _ in seen] == pytest.approx([k * 10.0 / stop * 8 for k in range(steps)])
        assert left == [pytest.approx(100.0 - 10.0 * steps)] and summary["total_s"] == 10.0 * steps
        assert model.run_info["fit"]["train_time_s"] == summary["total_s"]


def test_the_pass_keeps_its_least_and_training_its_share_when_the_budget_is_short(scenario) -> None:
    """The pass is never given less than its least (levels and WNOMP's APS of every pair), even past the share;
    when a caller's later work leaves no room at all, training still gets ``MIN_TRAIN_SHARE`` of the budget (with a
    progress bar that draws) and the pass its least: the fit runs over rather than leave the field one step."""
    from rflscm.train.trainer import MIN_TRAIN_SHARE

    extras: list[float | None] = []  # the time the pass may correct pairs beyond its least (None: all it has)

    def run(cost: PassCost, share: float = 0.5, **after: float) -> tuple[dict[str, float], list[float]]:
        clock, seen, left = StepClock(10.0), [], []
        model = timed_model(clock, seen)
        train = dataclasses.replace(model.config.train, finish_share=share)
        model.config = dataclasses.replace(model.config, train=train)
        model.finish_seconds = lambda clock, fresh=None: cost  # type: ignore[method-assign]

        def finish(progress=False, time_left=None, clock=None, extra_left=None):  # type: ignore[no-untyped-def]
            left.append(time_left())
            extras.append(None if extra_left is None else extra_left())

        model.finish_training = finish  # type: ignore[method-assign]
        return fit(model, scenario, progress=False, budget_s=100.0, clock=clock, **after), left

    # 48 s kept for later work; half of the 52 s left (26 s) is less than the least pass, 1.2 × 25 = 30 s: training
    # stops at 22 s (three steps, 30 s) and the pass is told its least, 30 s, past the budget's end
    summary, left = run(PassCost(80.0, 0.5, 25.0), after_s=40.0)
    assert summary["train_budget_s"] == pytest.approx(22.0) and summary["steps"] == 3
    assert left == [pytest.approx(30.0)]
    # pairs beyond the least only to the budget's end: 100 s less the 48 s kept and the 30 s trained
    assert extras == [pytest.approx(22.0)]
    # the least is kept beyond the pass's share too: a network whose every pair's fallback outlasts that share
    # (1.2 × 50 s against 0.2 × 100 s) trains 40 s and gives the pass its least, 60 s, rather than leave pairs with
    # a barely trained field
    summary, left = run(PassCost(80.0, 0.5, 50.0), share=0.2)
    assert summary["train_budget_s"] == pytest.approx(40.0) and left == [pytest.approx(60.0)]
    assert extras[-1] is None  # within the budget: every pair in the time it has
    summary, left = run(PassCost(80.0, 0.5, 50.0), share=0.2, after_s=40.0)  # and with 48 s kept after it: past it
    assert left[-1] == pytest.approx(60.0) and extras[-1] == pytest.approx(100.0 - 48.0 - summary["train_budget_s"])
    # the demo's evaluation of 200 pairs without training data (always rendered): 1.2 × 200 × 0.5 = 120 s of a 100 s
    # budget, nothing is left for the fit
    clock, seen, left = StepClock(10.0), [], []
    model = timed_model(clock, seen)
    model.finish_seconds = lambda clock, fresh=None: PassCost(50.0, 0.5, 20.0)  # type: ignore[method-assign]
    model.finish_training = lambda progress=False, time_left=None, clock=None, extra_left=None: left.append(time_left())  # type: ignore[method-assign]
    summary = fit(model, scenario, progress=True, budget_s=100.0, clock=clock, after_fresh=fresh_pairs(200))
    assert summary["train_budget_s"] == pytest.approx(MIN_TRAIN_SHARE * 100.0) and summary["steps"] == 2
    assert left == [pytest.approx(1.2 * 20.0)]  # the least pass, past the budget's end


def test_the_caller_renders_no_training_pair_only_its_pairs_without_training_reports() -> None:
    """A pair the pass corrects keeps its render and a pair it leaves is answered without the caller's render (WNOMP's
    APS, a borrowed APS, or the pass's own render), so the caller's reserve counts only its pairs without training
    reports and its other seconds."""
    from rflscm.train.trainer import FINISH_SAFETY, budget_split

    cost = PassCost(50.0, 0.5, 20.0)
    # nothing after the fit: the pass keeps its share of the budget (half of 100 s: less than 1.2 × 50)
    assert budget_split(cost, 100.0, 0.5) == (0.0, pytest.approx(50.0))
    # pairs without training data are always rendered by the caller: 1.2 × 200 × 0.5 = 120 s, the pass keeps its least
    after, kept = budget_split(cost, 100.0, 0.5, after_fresh=200)
    assert after == pytest.approx(120.0) and kept == pytest.approx(FINISH_SAFETY * cost.least_s)
    # an ample budget: the whole pass, and the caller's renders and other work
    after, kept = budget_split(cost, 1000.0, 0.5, after_s=5.0, after_fresh=200)
    assert kept == pytest.approx(60.0) and after == pytest.approx(FINISH_SAFETY * (100.0 + 5.0))


def test_halfway_the_budget_is_dealt_again_from_a_fresh_measurement_and_the_schedule_goes_on(
    scenario, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Before the first step the pass is measured cheap (12 s kept: training's share 88 s); halfway through that share
    it is measured again, dearer (48 s kept): the share becomes 52 s and training stops at the first step past it. The
    schedule never jumps back, and goes on from where it was; where the second measurement is cheaper, training gets
    the time back; before ``REPLAN_MIN_STEPS`` steps nothing is dealt again."""
    from rflscm.train import trainer

    clock, seen = StepClock(10.0), []
    model = timed_model(clock, seen)
    costs = iter([PassCost(10.0, 0.5), PassCost(40.0, 0.5)])
    model.finish_seconds = lambda clock, fresh=None, c=costs: next(c)  # type: ignore[method-assign]
    model.finish_training = lambda progress=False, time_left=None, clock=None: None  # type: ignore[method-assign]
    assert fit(model, scenario, progress=False, budget_s=100.0, clock=clock)["train_budget_s"] == pytest.approx(88.0)
    monkeypatch.setattr(trainer, "REPLAN_MIN_STEPS", 0)
    for second, stop, steps in ((PassCost(40.0, 0.5), 52.0, 6), (PassCost(0.0, 0.5), 100.0, 10)):
        clock, seen, left = StepClock(10.0), [], []
        model = timed_model(clock, seen)
        costs = iter([PassCost(10.0, 0.5), second])
        model.finish_seconds = lambda clock, fresh=None, c=costs: next(c)  # type: ignore[method-assign]
        model.finish_training = lambda progress=False, time_left=None, clock=None, seen=left: seen.append(time_left())  # type: ignore[method-assign]
        summary = fit(model, scenario, progress=False, budget_s=100.0, clock=clock)
        assert summary["train_budget_s"] == pytest.approx(stop) and summary["steps"] == steps
        positions = [p for _, p, _ in seen]
        assert positions == sorted(positions) and positions[:5] == pytest.approx([k * 10.0 / 88 * 8 for k in range(5)])
        assert left == [pytest.approx(100.0 - 10.0 * steps)]


def test_finish_share_must_be_a_fraction() -> None:
    from rflscm.errors import ConfigError
    from rflscm.models.rflscm.config import TrainConfig

    for bad in (0.0, 1.0, -0.1, 1.5):
        with pytest.raises(ConfigError, match=r"`train.finish_share` must be in \(0, 1\)"):
            TrainConfig(finish_share=bad)


def test_the_pass_estimate_is_measured_on_the_final_render(scenario) -> None:
    """``finish_seconds`` times two chunks of the real pass on the clock it is given (1 s between reads here): the
    first pays the per-cell setup, the second gives the per-pair render, preparation and fit; the total adds the
    λ and atoms choice, the dB mix's choice (a preparation, a fit and WNOMP's solve at each of its atom counts per λ
    pair) and WNOMP's solve of every pair (a budget's safety net), and an evaluation's render per pair is the render
    alone."""
    from rflscm.models.rflscm.corrections import (
        LAMBDA_PAIRS,
        LAMBDAS,
        LEVEL_PAIRS_PER_CELL,
        MIX_ATOMS,
        PAIR_CHUNK,
        WNOMP_ATOMS,
        WNOMP_PRIORS,
        PassTimes,
        _solve_sample,
    )

    model = RFLSCM.build(tiny_config(), GRID)
    model.prepare(scenario)
    ticks = iter(range(100))
    estimate = model.finish_seconds(lambda: float(next(ticks)))
    data = model._training().data
    pairs = int(data.observed.any(1).sum())
    n_first = n_second = min(pairs, PAIR_CHUNK)  # a spread chunk, then a chunk of a block as the pass takes them
    assert estimate.per_pair_s == pytest.approx(1 / n_second)
    cfg = model.config.corrections
    assert cfg.pair_posterior and cfg.wnomp_atoms
    each = 1 / n_second
    setup = max(0.0, 1 - n_first / n_second) * len(model.scene.cell_ids)  # every cell of the tiny scene is in it
    options = 1 + len(WNOMP_ATOMS) * len(WNOMP_PRIORS)  # no atoms, or each atom count with each prior
    solve = 1 / _solve_sample(torch.nonzero(data.observed.any(1)).squeeze(1)).numel()  # one tick over the sample
    lam_pairs = min(pairs, LAMBDA_PAIRS)
    expected = setup + pairs * 3 * each + options * lam_pairs * (1 + len(LAMBDAS)) * each
    expected += lam_pairs * (2 * each + len(MIX_ATOMS) * solve) + pairs * solve  # the dB mix's choice, the safety net
    assert estimate.total_s == pytest.approx(expected)
    assert PassTimes(setup, each, each, each, solve).total_s(cfg, pairs) == pytest.approx(expected)
    off = dataclasses.replace(cfg, wnomp_fallback=False, wnomp_atoms=False)  # neither: the λ choice alone
    plain = setup + pairs * 3 * each + lam_pairs * (1 + len(LAMBDAS)) * each
    assert PassTimes(setup, each, each, each, solve).total_s(off, pairs) == pytest.approx(plain)
    # the least pass: the levels' pairs rendered and prepared, and WNOMP's solve of every pair, timed on a spread
    # sample of them all (one clock read before and after)
    levels = min(pairs, LEVEL_PAIRS_PER_CELL * len(model.scene.cell_ids)) * 2 * each
    assert estimate.least_s == pytest.approx(setup + levels + 1.0)
    assert estimate.least_s < estimate.total_s


def test_a_callers_fresh_pairs_are_priced_by_the_chunks_of_its_calls(scenario) -> None:
    """Given a caller's fresh pairs, ``finish_seconds`` also times render chunks of them, cut as the caller's ``aps``
    calls will cut them, about ``FRESH_PAIRS`` pairs' worth (at least 2, at most ``FRESH_CHUNKS`` chunks), and prices
    every chunk there is at a set-up plus a rate per pair fitted to those times: a caller asking a few pairs at a
    time pays a set-up per call, not per ``PAIR_CHUNK`` pairs.  Pairs of cells the model does not know are skipped;
    without any known cell nothing is timed and the pass's own render rate stands in."""
    from rflscm.models.rflscm.corrections import PAIR_CHUNK
    from rflscm.models.rflscm.model import FRESH_CHUNKS

    model = RFLSCM.build(tiny_config(), GRID)
    model.prepare(scenario)
    cells = model.scene.cell_ids
    count = 5 * PAIR_CHUNK
    ids = np.concatenate([np.resize(cells, count), [cells.max() + 1]])  # the last pair's cell is unknown
    xyz = np.tile([5.0, -3.0, 1.5], (count + 1, 1))
    now, rendered = [0.0], []
    output = model.renderer.output

    def render(c, g, p):  # type: ignore[no-untyped-def]
        now[0] += 1.0 + 0.5 * len(c)  # a chunk's set-up 1 s, 0.5 s a pair
        rendered.append(len(c))
        return output(c, g, p)

    model.renderer.output = render  # type: ignore[method-assign]

    def priced(fresh: FreshPairs) -> float | None:
        rendered.clear()
        return model._fresh_render_s(fresh, 8.0, lambda: now[0])

    # one call: 5 full chunks, 2 of them timed
    assert priced(FreshPairs(ids, xyz)) == pytest.approx((5 * 1.0 + 0.5 * count) / count)
    assert rendered == [PAIR_CHUNK] * 2
    # 4 pairs a call: 80 chunks of 4, FRESH_CHUNKS of them timed, each chunk paying its set-up
    assert priced(FreshPairs(ids, xyz, np.arange(count + 1) // 4)) == pytest.approx((80 + 0.5 * count) / count)
    assert rendered == [4] * FRESH_CHUNKS
    # calls of 2 and 6 pairs in turn: the set-up and the rate fitted to chunks of both sizes
    mixed = np.repeat(np.arange(40), np.tile([2, 6], 20))
    assert priced(FreshPairs(ids[:160], xyz[:160], mixed)) == pytest.approx((40 + 0.5 * 160) / 160)
    assert sorted(set(rendered)) == [2, 6] and len(rendered) == FRESH_CHUNKS
    few = FreshPairs(ids[:5], xyz[:5])  # fewer than a chunk: one chunk of them all
    assert priced(few) == pytest.approx((1.0 + 2.5) / 5) and rendered == [5]
    stranger = FreshPairs(ids[-1:], xyz[-1:])
    assert priced(stranger) is None and rendered == []
    ticks = iter(range(1000))
    cost = model.finish_seconds(lambda: float(next(ticks)), stranger)
    assert cost.fresh_s is None and cost.fresh_pair_s == cost.per_pair_s
    cost = model.finish_seconds(lambda: now[0], few)
    assert cost.fresh_pair_s == cost.fresh_s == pytest.approx(3.5 / 5)
    with pytest.raises(ValueError, match="call keys"):
        FreshPairs(ids, xyz, np.zeros(3, np.int64))


def test_work_after_the_fit_is_kept_out_of_the_budget(scenario) -> None:
    """``after_s`` seconds and the renders of ``after_fresh`` pairs are kept free (×1.2) whatever the pass does; a
    caller's ``after_pairs`` (with training reports) cost no reserve but ask the pass to render the pairs it leaves
    itself (``render_rest``) where no render-free answer serves them."""
    clock, seen, left, rest = StepClock(10.0), [], [], []
    model = timed_model(clock, seen)

    def finish(progress=False, time_left=None, clock=None, render_rest=False, extra_left=None) -> None:  # type: ignore[no-untyped-def]
        left.append(time_left())
        rest.append(render_rest)

    model.finish_training = finish  # type: ignore[method-assign]
    told: list[FreshPairs | None] = []

    def finish_seconds(clock, fresh=None) -> PassCost:  # type: ignore[no-untyped-def]
        told.append(fresh)  # the fresh pairs' renders are timed on the pairs themselves: dearer than a training pair's
        return PassCost(10.0, 0.5, 1.0, fresh_s=None if fresh is None else 1.0)

    model.finish_seconds = finish_seconds  # type: ignore[method-assign]
    summary = fit(model, scenario, progress=False, budget_s=100.0, clock=clock, after_pairs=20, after_s=5.0)
    # kept after the fit: 1.2 × 5 = 6 s; for the pass 1.2 × 10 = 12 s: training stops at 82 s (9 steps)
    assert summary["train_budget_s"] == pytest.approx(82.0) and rest[-1] is True
    assert left == [pytest.approx(max(100.0 - 6.0 - summary["train_time_s"], 1.2))]
    left.clear()
    clock.now = 0.0
    assert told and all(f is None for f in told)
    fresh = fresh_pairs(20)
    summary = fit(model, scenario, progress=False, budget_s=100.0, clock=clock, after_fresh=fresh, after_s=5.0)
    # fresh pairs: all kept up front at their own rate, 1.2 × (20 × 1 s + 5 s) = 30 s; the pass 12 s: training stops
    # at 60 s (the first step end past 58 s)
    assert left == [pytest.approx(100.0 - 30.0 - 60.0)] and rest[-1] is False
    assert told[-1] is fresh and summary["after_kept_s"] == pytest.approx(30.0)  # told to the caller
