"""Process settings the CLI applies (rflscm.runtime)."""

from __future__ import annotations

import ctypes
import ctypes.util

import pytest

from rflscm import runtime


def _glibc() -> bool:
    name = ctypes.util.find_library("c")
    return bool(name) and hasattr(ctypes.CDLL(name), "gnu_get_libc_version")


def test_the_environment_wins_over_the_allocator_settings(monkeypatch) -> None:
    monkeypatch.setenv("MALLOC_MMAP_THRESHOLD_", "131072")
    assert runtime.keep_freed_memory() is False


@pytest.mark.skipif(not _glibc(), reason="glibc's mallopt only")
def test_glibc_takes_the_allocator_settings(monkeypatch) -> None:
    for key in runtime.MALLOC_ENV:
        monkeypatch.delenv(key, raising=False)
    assert runtime.keep_freed_memory() is True
    assert set(runtime.MALLOC_ENV) == {"MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_"}
    assert all(int(v) >= 1 << 30 for v in runtime.MALLOC_ENV.values())
