"""Every command's ``--help`` speaks its users' language: a unit beside every number, no ``%%``, no ``<bool>``,
no square brackets for Rich to swallow, no internal references (spec sections, commit ids, issue numbers).

Written over every registered command, so a command added later is checked too."""

from __future__ import annotations

import re
import typing

import pytest
import typer.main
from typer.testing import CliRunner

from rflscm.cli import _register_commands, app

_register_commands()
ROOT = typer.main.get_command(app)
COMMANDS = sorted(getattr(ROOT, "commands", {}))
UNITS = {
    "dBm",
    "dB",
    "deg",
    "m",
    "m²",
    "s",
    "min",
    "Hz",
    "GHz",
    "%",
    "count",
    "cells",
    "threads",
    "grids",
    "steps",
    "fraction",
    "integer",
    "passes",
    "seeds",
    "points",
    "bins",
    "beams",
    "rays",
    "samples",
}
"""What may stand in parentheses in a numeric option's help: ``(dBm)``, ``(deg, clockwise)``, ``(count; …)``."""
INTERNAL = [r"SPEC\s*§", r"§\s*\d", r"\bissue\s*#?\d+", r"\b(?=[0-9a-f]*\d)(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}\b"]


def _help(*args: str) -> str:
    result = CliRunner().invoke(app, [*args, "--help"], env={"COLUMNS": "200", "NO_COLOR": "1"})
    assert result.exit_code == 0, result.output
    return result.output


def _numeric(param: object) -> bool:
    descriptor = getattr(param, "type_descriptor", None)
    if descriptor is not None:
        annotation = descriptor.annotation
        return any(a in (int, float) for a in (typing.get_args(annotation) or (annotation,)))
    name = getattr(getattr(param, "type", None), "name", "")
    return name in ("integer", "float", "integer range", "float range")


def _has_unit(text: str) -> bool:
    groups = re.findall(r"\(([^()]*)\)", text)
    return any(set(re.split(r"[\s,;:]+", group.strip())) & UNITS for group in groups)


def _params(name: str | None) -> list:
    command = ROOT if name is None else ROOT.commands[name]  # type: ignore[attr-defined]
    return [p for p in command.params if getattr(p, "param_type_name", "") == "option"]


def test_every_command_is_checked() -> None:
    assert {"evaluate", "optimize", "predict", "train"} <= set(COMMANDS)


@pytest.mark.parametrize("name", [None, *COMMANDS])
def test_help_has_units_and_no_noise(name: str | None) -> None:
    text = _help(*([name] if name else []))
    assert "%%" not in text
    assert "<bool>" not in text
    for pattern in INTERNAL:
        found = re.search(pattern, text, flags=re.IGNORECASE)
        assert found is None, f"{name}: internal reference {found.group(0)!r} in --help"
    for param in _params(name):
        flag = param.opts[0]
        help_text = param.help or ""
        assert help_text, f"{name} {flag}: no help line"
        unescaped = re.search(r"(?<!\\)\[[^\]]*\]", help_text)
        assert unescaped is None, f"{name} {flag}: {unescaped.group(0)!r} is Rich markup and vanishes from --help"
        if _numeric(param) and not getattr(param, "is_flag", False):
            assert _has_unit(help_text), f"{name} {flag}: a number without a unit in its help: {help_text!r}"


def test_help_shows_units_and_choices() -> None:
    text = _help("optimize")
    assert "(dBm)" in text and "(dB)" in text
    assert "<coverage|sinr|weighted>" in text and "<cd|de>" in text


def test_checker_catches_what_it_should() -> None:
    assert not _has_unit("Coverage threshold on best-server RSRP [dBm].")
    assert _has_unit("Coverage threshold on best-server RSRP (dBm).")
    assert _has_unit("Azimuth offsets (deg, clockwise).")
    assert re.search(INTERNAL[-1], "default: c7460d6") and not re.search(INTERNAL[-1], "default: deadbeef is a word")
