"""An interruption while Ray waits comes out as the interruption, not as Ray's SystemError (issue 27)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

import rflscm.parallel.engine as engine_module
from rflscm.parallel.engine import Engine, ray_session


class Stop(Exception):
    """Stands for the CLI's interruption, raised by its signal handler."""


@pytest.fixture
def running_ray(monkeypatch: pytest.MonkeyPatch) -> None:
    fake = SimpleNamespace(is_initialized=lambda: True, shutdown=lambda: None)  # joined: nothing started or stopped
    monkeypatch.setattr(engine_module, "import_ray", lambda: fake)


def test_a_signal_handlers_exception_inside_ray_is_raised_as_itself(running_ray: None) -> None:
    # what Ray's C code makes of an exception a signal handler raised while it waited (seen on Ctrl-C in optimize)
    with pytest.raises(Stop), ray_session(Engine(workers=2)):
        try:
            raise Stop("interrupted")
        except Stop as stop:
            raise SystemError("<built-in method __new__> returned a result with an exception set") from stop


def test_a_plain_system_error_is_left_alone(running_ray: None) -> None:
    with pytest.raises(SystemError, match="plain"), ray_session(Engine(workers=2)):
        raise SystemError("plain")
