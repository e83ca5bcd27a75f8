"""The artefact makers in scripts/ still make the artefacts that ship."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_make_patch_element_writes_the_shipped_file(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    script = ROOT / "scripts" / "make_patch_element.py"
    spec = importlib.util.spec_from_file_location("make_patch_element", script)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    shipped = module.OUT
    assert shipped.is_file() and shipped.parent.name == "antennas"
    monkeypatch.setattr(module, "OUT", tmp_path / shipped.name)
    module.main()
    assert (tmp_path / shipped.name).read_bytes() == shipped.read_bytes()
