"""A damaged archive that makes ``zipfile.is_zipfile`` raise is "not an archive", and the checkpoint and APS-cache
readers refuse it in one line (the fault-injection test found a flipped byte doing this)."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import pytest

from rflscm.data.safe_io import is_zip_archive
from rflscm.errors import CheckpointError


def multi_disk_zip(path: Path) -> Path:
    """A zip whose zip64 end locator claims two disks: ``zipfile.is_zipfile`` raises ``BadZipFile`` on it."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as z:
        z.writestr("a", "x")
    data = bytearray(buffer.getvalue())
    end = data.rfind(b"PK\x05\x06")
    locator = b"PK\x06\x07" + (0).to_bytes(4, "little") + (0).to_bytes(8, "little") + (2).to_bytes(4, "little")
    path.write_bytes(bytes(data[:end] + locator + data[end:]))
    with pytest.raises(zipfile.BadZipFile):
        zipfile.is_zipfile(path)
    return path


def test_a_zip_that_chokes_is_zipfile_is_not_an_archive(tmp_path: Path) -> None:
    assert is_zip_archive(multi_disk_zip(tmp_path / "bad.zip")) is False
    good = tmp_path / "good.zip"
    with zipfile.ZipFile(good, "w") as z:
        z.writestr("a", "x")
    assert is_zip_archive(good) is True


def test_the_readers_refuse_it_in_one_line(tmp_path: Path) -> None:
    from rflscm.eval.cache import APSCacheError, ScenarioAPS
    from rflscm.models.base import read_checkpoint

    bad = multi_disk_zip(tmp_path / "bad.ckpt")
    with pytest.raises(CheckpointError, match="not an rflscm checkpoint"):
        read_checkpoint(bad)
    with pytest.raises(APSCacheError, match="not an rflscm APS cache"):
        ScenarioAPS.load(bad)
