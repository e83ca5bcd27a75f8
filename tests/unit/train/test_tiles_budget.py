"""A tiled run's budget is split over the tiles by their training pairs so that the whole run keeps it (issue 29)."""

from __future__ import annotations

import time

import pytest

import rflscm.train.tiles as tiles
from rflscm.train.tiles import TileResult, queue_budgets, schedule, serial_runner, tile_budget


def test_a_tile_gets_its_weights_share_of_the_time_its_queue_has_left() -> None:
    assert tile_budget(None, 1.0, 3.0) is None
    assert tile_budget(100.0, 1.0, 4.0, now=40.0) == pytest.approx(15.0)  # 60 s, a quarter of the queue's pairs
    assert tile_budget(100.0, 3.0, 4.0, now=40.0) == pytest.approx(45.0)
    assert tile_budget(100.0, 5.0, 5.0, now=40.0) == pytest.approx(60.0)  # the queue's last tile: all that is left
    assert tile_budget(100.0, 1.0, 2.0, now=120.0) == 1.0  # the time is gone: every tile still gets a model


def test_tiles_are_dealt_heaviest_first_to_the_least_loaded_queue() -> None:
    weights = [10.0, 50.0, 20.0, 30.0, 5.0]
    assert schedule(weights, 1) == [[1, 3, 2, 0, 4]]
    two = schedule(weights, 2)
    assert two == [[1, 0], [3, 2, 4]]  # 50 | 30; 20 to the 30 (50 | 50); 10 to the first (60 | 50); 5 to the 50
    assert sorted(i for q in two for i in q) == list(range(5))
    assert [sum(weights[i] for i in q) for q in two] == [60.0, 55.0]
    assert schedule([1.0, 1.0], 8) == [[0], [1]]  # more slots than tiles: no empty queue
    assert schedule([], 2) == []
    assert queue_budgets(weights, [3, 2, 4]) == [(30.0, 55.0), (20.0, 25.0), (5.0, 5.0)]


def test_the_largest_tile_is_not_starved_and_no_tile_gets_the_minimum() -> None:
    # the 1 002-cell run: nine tiles of 7.5k to 146k pairs on two workers, each using its whole budget; cut by
    # sites and shared equally, the last started with nothing left (1 s)
    weights = [9130, 60510, 54236, 7534, 63334, 20234, 146446, 84165, 18353]
    deadline, ends = 900.0, {}
    queues = schedule(weights, 2)
    loads = [sum(weights[i] for i in q) for q in queues]
    assert max(loads) / min(loads) < 1.05  # the two workers carry about the same pairs
    for queue, load in zip(queues, loads, strict=True):
        t = 0.0
        for i, (w, rest) in zip(queue, queue_budgets(weights, queue), strict=True):
            budget = tile_budget(deadline, w, rest, now=t)
            assert budget == pytest.approx(deadline * w / load)  # its pairs' share of its worker's time
            t += budget
            ends[i] = t
    assert len(ends) == len(weights) and max(ends.values()) == pytest.approx(deadline)
    largest = tile_budget(deadline, 146446, sum(weights) / 2, now=0.0)
    assert largest is not None and largest > 250.0  # about its share of the pairs, not a ninth of the time


def test_the_serial_runner_hands_each_tile_its_share_of_the_time_left_when_it_starts(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    given: dict[int, float | None] = {}
    clock = [1000.0]

    def fake_run(job: int, budget: float | None, deadline: float | None = None) -> TileResult:
        given[job] = budget
        clock[0] += 10.0 if job == 2 else float(budget or 0.0)  # the first (heaviest) ends early, the rest use all
        return TileResult(None, {"job": job}, {}, 0.0, 0, budget)  # type: ignore[arg-type]

    monkeypatch.setattr(tiles, "run_tile", fake_run)
    monkeypatch.setattr(time, "time", lambda: clock[0])
    done: list[TileResult] = []
    results = serial_runner([1.0, 1.0, 2.0], lambda i: i, 1100.0, done.append)  # type: ignore[arg-type, return-value]
    assert given[2] == pytest.approx(50.0)  # half the pairs: half of 100 s
    assert given[0] == pytest.approx(45.0)  # 90 s left, two equal tiles
    assert given[1] == pytest.approx(45.0)
    assert [r.payload["job"] for r in results] == [0, 1, 2]  # in tile order
    assert [r.payload["job"] for r in done] == [2, 0, 1]  # in the order they ran
