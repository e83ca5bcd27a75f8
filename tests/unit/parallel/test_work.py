"""The ordered map over Ray workers (rflscm.parallel.work): the serial order, a bounded window, one-line failures."""

from __future__ import annotations

import sys
import time
from collections.abc import Iterator

import pytest

from rflscm.errors import ConfigError, RflscmError
from rflscm.parallel.engine import OBJECT_STORE_BYTES, Engine
from rflscm.parallel.work import JOBS_PER_WORKER, mapper


def slow_square(job: int) -> int:
    time.sleep(0.05 * (job % 3 == 0))  # uneven jobs: results finish out of order
    return job * job


def refuse(job: int) -> int:
    if job == 3:
        raise ConfigError("job 3 is refused")
    return job


def crash(job: int) -> int:
    if job == 2:
        raise ZeroDivisionError("division by zero in job 2")
    return job


def test_one_worker_is_the_builtin_map_in_process() -> None:
    with mapper(Engine()) as run:
        assert run is map


@pytest.fixture(scope="module")
def local_ray() -> Iterator[None]:
    ray = pytest.importorskip("ray")
    from ray import cloudpickle

    cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the workers cannot import this test module
    ray.init(num_cpus=2, object_store_memory=OBJECT_STORE_BYTES, include_dashboard=False, log_to_driver=False)
    yield
    ray.shutdown()
    cloudpickle.unregister_pickle_by_value(sys.modules[__name__])


@pytest.mark.slow
def test_workers_give_the_serial_results_in_order_and_draw_jobs_as_they_go(local_ray: None) -> None:
    drawn: list[int] = []

    def jobs() -> Iterator[int]:
        for j in range(20):
            drawn.append(j)
            yield j

    with mapper(Engine(workers=2)) as run:
        results = []
        for result in run(slow_square, jobs()):
            if not results:  # the first result: no more than the window was sent ahead of it
                assert len(drawn) <= JOBS_PER_WORKER * 2 + 1
            results.append(result)
    assert results == [j * j for j in range(20)]


@pytest.mark.slow
def test_a_workers_error_of_ours_comes_back_as_itself_and_any_other_as_one_line(local_ray: None) -> None:
    with mapper(Engine(workers=2)) as run, pytest.raises(ConfigError, match="job 3 is refused"):
        list(run(refuse, range(8)))
    with mapper(Engine(workers=2), "a trace") as run, pytest.raises(RflscmError) as failed:
        list(run(crash, range(8)))
    message = str(failed.value)
    assert message.startswith("a Ray worker failed on a trace:") and "division by zero" in message
    assert "\n" not in message


def test_cuda_workers_on_a_cluster_without_a_gpu_is_a_clear_error(monkeypatch: pytest.MonkeyPatch) -> None:
    from types import SimpleNamespace

    import rflscm.parallel.engine as engine_module

    joined = SimpleNamespace(
        is_initialized=lambda: True,  # joined: nothing started or stopped
        shutdown=lambda: None,
        remote=lambda **options: lambda cls: cls,
        cluster_resources=lambda: {"CPU": 16.0},
    )
    monkeypatch.setattr(engine_module, "import_ray", lambda: joined)
    with pytest.raises(ConfigError, match="no GPU"), mapper(Engine(workers=2, address="auto"), gpus=True):
        pass
