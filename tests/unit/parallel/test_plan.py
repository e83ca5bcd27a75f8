"""Chunk planning and merging of rflscm.parallel with a fake predictor (no Ray): the calls the serial path makes,
chunked and merged back in the original order, fill a cache that answers exactly as the serial one."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch

from rflscm.errors import RflscmError, UnsupportedError
from rflscm.eval.cache import APSCache, ScenarioAPS
from rflscm.geometry import AngleGrid
from rflscm.models.source import Predicts
from rflscm.parallel.aps import (
    FilledAPSCache,
    answer,
    fill_cache,
    gather,
    prediction_requests,
    render_requests,
    scatter,
)
from rflscm.parallel.plan import cache_misses, predict_blocks, split_even

GRID = AngleGrid(num_el=4, num_az=6, el_min_deg=-90.0, el_step_deg=45.0)


class FakeSource(Predicts):
    """APS from the pair's ids and the size of the call (a batch-dependent answer, like a real model may be);
    records its calls.  Refuses cell 99."""

    name, angle_grid, device, supports_unseen_grids, fingerprint, run_info = (
        "fake",
        GRID,
        torch.device("cpu"),
        True,
        None,
        {},
    )

    def __init__(self) -> None:
        self.calls: list[list[tuple[int, int]]] = []

    def aps(self, cell_ids, grid_ids, grid_xyz=None) -> torch.Tensor:
        if 99 in np.asarray(cell_ids):
            raise UnsupportedError("no cell 99")
        self.calls.append(list(zip(np.asarray(cell_ids).tolist(), np.asarray(grid_ids).tolist())))
        n = len(cell_ids)
        bins = (np.asarray(cell_ids) * 7 + np.asarray(grid_ids)) % GRID.num_bins
        x = torch.zeros(n, GRID.num_bins)
        x[torch.arange(n), torch.from_numpy(bins)] = torch.from_numpy(np.asarray(grid_ids, np.float32) + 1 / n)
        x[:, 0] = float(n)  # depends on the batch: a wrong plan gives another value
        return x

    def level_offset_db(self, cell_ids, beam_type, grid_ids=None):
        return None

    def content_sha256(self) -> str:
        return "fake"


class FakeScenario:
    def __init__(self, grid_ids: np.ndarray, cell_ids: np.ndarray | None = None) -> None:
        self.grids = pd.DataFrame({"grid_id": grid_ids, "x": grid_ids * 1.0, "y": 0.0, "z": 1.5})
        self._cells = np.arange(3) if cell_ids is None else cell_ids
        self.cells = {1: pd.DataFrame({"cell_id": self._cells, "x": 0.0, "y": 0.0, "z": 25.0})}
        heard = grid_ids[len(grid_ids) // 2]  # round 1 hears every cell at the middle grid only
        self.measurements = pd.DataFrame(
            {"round": 1, "cell_id": self._cells, "grid_id": heard, "beam_type": "ssb", "beam_id": 0, "rsrp_dbm": -90.0}
        )

    def cell_ids(self) -> np.ndarray:
        return self._cells

    def grid_ids(self) -> np.ndarray:
        return self.grids["grid_id"].to_numpy()


def test_predict_blocks_are_cell_by_cell_in_order_and_at_most_chunk_long() -> None:
    cells = np.array([5, 3, 5, 3, 5, 5, 3])
    blocks = predict_blocks(cells, chunk=2)
    assert [b.tolist() for b in blocks] == [[1, 3], [6], [0, 2], [4, 5]]


def test_cache_misses_replays_the_cache_asking_each_new_pair_once() -> None:
    requests = [
        (np.array([1, 1, 1]), np.array([4, 5, 4])),
        (np.array([1, 2]), np.array([5, 5])),
        (np.array([2]), np.array([5])),
    ]
    calls = cache_misses(requests, {(1, 5)})
    assert [list(zip(c.cell_ids.tolist(), c.grid_ids.tolist())) for c in calls] == [[(1, 4)], [(2, 5)]]
    # the same calls the real cache makes on its source
    source = FakeSource()
    cache = APSCache(source)
    cache.aps(np.array([1]), np.array([5]))
    source.calls.clear()
    for cells, grids in requests:
        cache.aps(cells, grids)
    assert source.calls == [[(1, 4)], [(2, 5)]]


def test_split_even_keeps_every_item_once_in_order() -> None:
    sizes = [5, 1, 1, 1, 9, 2, 2, 3]
    for k in range(1, 12):
        ranges = split_even(sizes, k)
        assert [i for r in ranges for i in r] == list(range(len(sizes)))
        assert 1 <= len(ranges) <= k
    assert split_even([], 3) == []
    assert [list(r) for r in split_even([1, 1, 1, 1], 2)] == [[0, 1], [2, 3]]


@pytest.mark.parametrize("num_chunks", [1, 2, 3, 7])
def test_a_filled_cache_predicts_what_the_serial_cache_predicts(num_chunks: int) -> None:
    rng = np.random.default_rng(0)
    pairs = pd.DataFrame({"cell_id": rng.integers(0, 4, 40), "grid_id": rng.integers(0, 9, 40)})
    pairs.loc[3] = (99, 1)  # refused: the serial path meets the refusal itself
    scenario = FakeScenario(np.arange(9))
    serial = APSCache(FakeSource())
    order: list[int] = []

    def run(chunks):  # workers answer out of order; the merge must still be in the chunks' order
        answers = {}
        for k in reversed(range(len(chunks))):
            order.append(k)
            answers[k] = answer(FakeSource(), chunks[k])
        return [answers[k] for k in range(len(chunks))]

    source = FakeSource()
    filled = FilledAPSCache(source)
    requests = prediction_requests(pairs)
    filled_pairs = fill_cache(filled, scenario, requests, num_chunks, run)  # type: ignore[arg-type]
    assert filled_pairs == len(pairs.drop_duplicates()) - 1 and len(order) >= 1
    ok = pairs[pairs["cell_id"] != 99]
    for cells, grids in prediction_requests(ok):
        assert torch.equal(filled.aps(cells, grids), serial.aps(cells, grids))
    assert source.calls == []  # everything came from the "workers"
    with pytest.raises(UnsupportedError):
        filled.aps(np.array([99]), np.array([1]))


def test_gather_refuses_a_worker_that_answered_the_wrong_shape() -> None:
    tasks = [(np.array([1, 1]), np.array([2, 3]), None), (np.array([2]), np.array([2]), None)]
    chunks = scatter(tasks, 2)
    good = [answer(FakeSource(), c) for c in chunks]
    assert len(gather(chunks, good)) == 2
    with pytest.raises(RflscmError, match="answered 1 APS rows"):
        gather(chunks, [[good[0][0][:1]], good[1]])
    with pytest.raises(RflscmError, match="answers came back"):
        gather(chunks, good[:1])


def test_the_optimisers_render_reads_a_filled_cache_and_gets_the_serial_aps() -> None:
    scenario = FakeScenario(np.arange(0, 50, 2), np.array([3, 7]))
    source = FakeSource()
    filled = FilledAPSCache(source)
    requests = render_requests(source, scenario, chunk=1024)
    # the grids within 1.25 × the farthest report (the middle grid, x = 24 m) of the cells at x = 0: x <= 30 m
    assert [g.tolist() for _, g in requests] == [list(range(0, 31, 2))] * 2
    fill_cache(filled, scenario, requests, 2, lambda chunks: [answer(FakeSource(), c) for c in chunks])  # type: ignore[arg-type]
    parallel = ScenarioAPS.render(filled, scenario)  # type: ignore[arg-type]
    serial = ScenarioAPS.render(FakeSource(), scenario)  # type: ignore[arg-type]
    assert source.calls == [] and parallel.source_sha256 == serial.source_sha256 == "fake"
    for a, b in zip(parallel.aps, serial.aps):
        assert torch.equal(a, b)
    assert all(np.array_equal(a, b) for a, b in zip(parallel.bins, serial.bins))
