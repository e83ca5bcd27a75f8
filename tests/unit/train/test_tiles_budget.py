"""A tiled run's budget is split over the tiles so that the whole run keeps it (issue 29)."""

from __future__ import annotations

import time

import pytest

import rflscm.train.tiles as tiles
from rflscm.train.tiles import TileResult, serial_runner, tile_budget


def test_a_tile_gets_the_time_left_over_the_rounds_of_tiles_left() -> None:
    assert tile_budget(None, 3, 1) is None
    assert tile_budget(100.0, 4, 1, now=40.0) == pytest.approx(15.0)  # serial: 60 s over 4 tiles
    assert tile_budget(100.0, 4, 2, now=40.0) == pytest.approx(30.0)  # two at once: 2 rounds
    assert tile_budget(100.0, 3, 2, now=40.0) == pytest.approx(30.0)  # ⌈3/2⌉ = 2 rounds
    assert tile_budget(100.0, 1, 8, now=40.0) == pytest.approx(60.0)
    assert tile_budget(100.0, 2, 1, now=120.0) == 1.0  # the time is gone: every tile still gets a model


def test_the_serial_runner_hands_each_tile_the_time_left_when_it_starts(monkeypatch: pytest.MonkeyPatch) -> None:
    given: list[float | None] = []
    clock = [1000.0]

    def fake_run(job: int, budget: float | None, deadline: float | None = None) -> TileResult:
        given.append(budget)
        clock[0] += 10.0 if job == 0 else 30.0  # the first tile ends early, the second uses its time
        return TileResult(None, {}, {}, 0.0, 0, budget)  # type: ignore[arg-type]

    monkeypatch.setattr(tiles, "run_tile", fake_run)
    monkeypatch.setattr(time, "time", lambda: clock[0])
    done: list[TileResult] = []
    results = serial_runner(3, lambda i: i, 1090.0, done.append)  # type: ignore[arg-type, return-value]
    assert given == pytest.approx([30.0, 40.0, 50.0])  # 90/3; then 80/2; then what is left: 50
    assert len(results) == len(done) == 3
