"""Issue 25, deliverable 4: `--preset`, `--config FILE.yaml` and `--set SECTION.KEY=VALUE` on top of the preset."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pytest

from rflscm.cli.overrides import model_config
from rflscm.config import apply_sets, from_dict, merge_config, parse_set
from rflscm.errors import ConfigError


@dataclass(frozen=True)
class _Inner:
    rate: float = 0.1
    steps: int = 10
    flag: bool = False
    cap: float | None = None


@dataclass(frozen=True)
class _Outer:
    inner: _Inner = field(default_factory=_Inner)
    name: str = "a"
    table: dict[str, float] = field(default_factory=dict)


def test_set_values_are_read_as_yaml_and_coerced_to_the_field_type() -> None:
    data = apply_sets(
        _Outer,
        {"inner": {"steps": 3}},
        [
            "inner.rate=1e-3",  # YAML 1.1 reads 1e-3 as text; the float field takes it as a number
            "inner.flag=true",
            "inner.cap=null",
            "name=b",
            "table.x=2",
        ],
    )
    cfg = from_dict(_Outer, data)
    assert cfg == _Outer(_Inner(rate=0.001, steps=3, flag=True, cap=None), "b", {"x": 2})
    assert isinstance(cfg.inner.rate, float)
    assert apply_sets(_Outer, {}, ["inner.cap=2.5"])["inner"]["cap"] == 2.5


@pytest.mark.parametrize(
    ("item", "message"),
    [
        ("inner.stepz=3", r"--set inner.stepz=3: unknown key `stepz` in `inner`; valid keys: cap, flag, rate, steps\."),
        ("model.prior=1", r"unknown key `model` in the top level; valid keys: inner, name, table\."),
        ("inner.steps=abc", r"`inner.steps` must be an integer \(got 'abc'\)"),
        ("inner.flag=maybe", r"`inner.flag` must be true or false"),
        ("name.x=1", r"`name` is a value, not a section"),
        ("inner.steps", r"write SECTION.KEY=VALUE"),
    ],
)
def test_set_errors_name_the_item_and_the_valid_keys(item: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        apply_sets(_Outer, {}, [item])


def test_parse_set_and_merge() -> None:
    assert parse_set("a.b=[1, 2]") == (["a", "b"], [1, 2])
    assert merge_config({"a": {"x": 1, "y": 2}, "b": 3}, {"a": {"y": 5}}) == {"a": {"x": 1, "y": 5}, "b": 3}


def test_a_config_yaml_overrides_the_chosen_preset_not_the_bare_defaults(tmp_path: Path) -> None:
    from rflscm.models.rflscm import RFLSCM

    quick = RFLSCM.build("quick").config
    bare = RFLSCM.build(None).config
    assert quick.field.delta_rank != bare.field.delta_rank  # else this test could not tell them apart
    user = tmp_path / "mine.yaml"
    user.write_text("train: {steps: 123}\n")
    data = model_config("rflscm", str(user), None, ["prior.enabled=false", "hitam.top_k=4"])
    cfg = RFLSCM.build(data).config
    assert cfg.train.steps == 123 and cfg.field == quick.field  # quick kept where not overridden
    assert cfg.prior.enabled is False and cfg.hitam.top_k == 4
    full = RFLSCM.build(model_config("rflscm", str(user), "full", [])).config
    assert full.field == RFLSCM.build("full").config.field and full.train.steps == 123
    assert model_config("rflscm", "quick", None, []) == "quick"  # nothing to override: the preset as before
    user.write_text("model: {prior: {enabled: false}}\n")
    with pytest.raises(
        ConfigError, match=r"mine.yaml: unknown key\(s\) 'model'.*valid keys: corrections, decoder, field"
    ):
        model_config("rflscm", str(user), None, [])
    with pytest.raises(ConfigError, match="name two presets"):
        model_config("rflscm", "quick", "full", [])


@dataclass(frozen=True)
class _Switch:
    on: bool | _Inner = True


def test_a_switch_that_may_carry_settings_takes_a_mapping_and_set_reaches_into_it() -> None:
    """A field typed ``bool | Dataclass`` (``corrections.wnomp_fallback``) reads true/false or a mapping of the
    dataclass's settings; ``--set`` can set the switch or one setting (the others at their defaults); a bad key or
    value in the mapping is named as the dataclass's, not as a failed bool."""
    assert from_dict(_Switch, {"on": False}).on is False
    assert from_dict(_Switch, {"on": {"steps": 3}}).on == _Inner(steps=3)
    assert from_dict(_Switch, apply_sets(_Switch, {}, ["on.steps=4"])).on == _Inner(steps=4)
    assert from_dict(_Switch, apply_sets(_Switch, {"on": {"steps": 4}}, ["on=false"])).on is False
    with pytest.raises(ConfigError, match=r"unknown key `stepz` in `on`; valid keys: cap, flag, rate, steps"):
        apply_sets(_Switch, {}, ["on.stepz=4"])
    with pytest.raises(ConfigError, match=r"unknown key\(s\) 'stepz' in `on`"):
        from_dict(_Switch, {"on": {"stepz": 4}})
    with pytest.raises(ConfigError, match=r"`on` must be true or false"):
        from_dict(_Switch, {"on": "maybe"})


def test_settings_a_command_chooses_sit_under_the_users_yaml_and_set(tmp_path: Path) -> None:
    """``model_config(..., under=)``: the demo's WNOMP settings for RF-LSCM's fallback apply over the preset, and the
    user's YAML and ``--set`` override them."""
    from rflscm.models.rflscm import RFLSCM
    from rflscm.models.wnomp import WNOMPConfig

    under = {"corrections": {"wnomp_fallback": {"k_max": 2, "tolerance": 0.05}}}
    cfg = RFLSCM.build(model_config("rflscm", "quick", None, [], under)).config
    assert cfg.corrections.wnomp_fallback == WNOMPConfig(k_max=2, tolerance=0.05)
    assert cfg.field == RFLSCM.build("quick").config.field
    cfg = RFLSCM.build(model_config("rflscm", "quick", None, ["corrections.wnomp_fallback=false"], under)).config
    assert cfg.corrections.wnomp_fallback is False
    user = tmp_path / "mine.yaml"
    user.write_text("corrections: {wnomp_fallback: {k_max: 4}}\n")
    cfg = RFLSCM.build(model_config("rflscm", str(user), None, [], under)).config
    assert cfg.corrections.wnomp_fallback == WNOMPConfig(k_max=4, tolerance=0.05)  # merged key by key


def test_a_bad_setting_inside_the_fallback_is_named_where_it_was_given() -> None:
    """WNOMP's checks name their keys ``model.…`` (where its settings sit in a WNOMP run); inside RF-LSCM's
    ``corrections.wnomp_fallback`` the same error names that path, and a WNOMP run's error stays ``model.…``."""
    from rflscm.models.rflscm import RFLSCM
    from rflscm.models.wnomp import wnomp_config

    with pytest.raises(ConfigError, match=r"^`corrections\.wnomp_fallback\.k_max` must be >= 1 \(got 0\)\.$"):
        RFLSCM.build(model_config("rflscm", "quick", None, ["corrections.wnomp_fallback.k_max=0"]))
    with pytest.raises(ConfigError, match=r"^`model\.k_max` must be >= 1 \(got 0\)\.$"):
        wnomp_config({"k_max": 0})
