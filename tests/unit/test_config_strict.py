"""Issue 14, items 2, 3 and 10: every YAML read is strict (encoding, duplicate keys, required keys)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import pytest

from rflscm.config import from_dict, load_config, load_yaml
from rflscm.data.geo import Origin
from rflscm.errors import ConfigError
from rflscm.models.rflscm import RFLSCM


@dataclass(frozen=True)
class _Needs:
    a: int
    b: float = 1.0


def test_missing_required_key_is_named() -> None:
    with pytest.raises(ConfigError, match=r"`origin` is missing required key\(s\) 'lon'"):
        from_dict(Origin, {"lat": 48.14}, prefix="origin")
    with pytest.raises(ConfigError, match=r"_Needs is missing required key\(s\) 'a'"):
        from_dict(_Needs, {"b": 2.0})


def test_nan_is_not_a_number_for_a_setting() -> None:
    with pytest.raises(ConfigError, match=r"`b` must be a number \(got .nan\)"):
        from_dict(_Needs, {"a": 1, "b": float("nan")})


def test_duplicate_keys_at_any_depth(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_text("train:\n  steps: 10\n  lr_decay: 0.1\n  steps: 20\n")
    with pytest.raises(
        ConfigError, match=r"c.yaml line 4: key 'steps' appears twice in the same mapping \(first on line 2\)"
    ):
        load_yaml(path)
    with pytest.raises(ConfigError, match="appears twice"):
        RFLSCM.build(str(path))  # model configs go through the same loader


def test_encoding_folder_and_missing_file(tmp_path: Path) -> None:
    path = tmp_path / "c.yaml"
    path.write_bytes(b"a: 1\nb: caf\xe9\n")
    with pytest.raises(ConfigError, match=r"c.yaml line 2: byte 0xe9 is not UTF-8 text"):
        load_yaml(path)
    with pytest.raises(ConfigError, match="is a folder"):
        load_yaml(tmp_path)
    with pytest.raises(ConfigError, match="file not found"):
        load_config(_Needs, tmp_path / "none.yaml")
    path.write_bytes(b"\xef\xbb\xbfa: 1\n")  # a UTF-8 BOM is fine
    assert load_config(_Needs, path) == _Needs(a=1)
