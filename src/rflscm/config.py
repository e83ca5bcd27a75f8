"""Typed configuration: frozen dataclasses, loaded from YAML with strict keys.

Every config in the package is a frozen dataclass whose fields carry their
defaults, so one glance at the class shows every default.  :func:`from_dict`
builds nested dataclasses from plain mappings and rejects unknown keys with a
message that lists the valid ones; :func:`to_dict` is its inverse.
"""

from __future__ import annotations

import dataclasses
import os
import stat
import types
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

from rflscm.errors import ConfigError, RflscmError

T = TypeVar("T")


def _is_dataclass_type(tp: object) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


def _coerce(tp: Any, value: Any, where: str) -> Any:
    """Convert a YAML value to the annotated field type ``tp``."""
    origin = typing.get_origin(tp)
    args = typing.get_args(tp)
    if _is_dataclass_type(tp):
        if isinstance(value, tp):
            return value
        if not isinstance(value, dict):
            raise ConfigError(f"`{where}` must be a mapping (got {value!r}).")
        return from_dict(tp, value, prefix=where)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        errors: list[str] = []
        for arg in args:
            if arg is type(None):
                continue
            try:
                return _coerce(arg, value, where)
            except ConfigError as exc:
                # a mapping's error is its dataclass's (a bad key or value in it), not another member's type
                errors.insert(0 if isinstance(value, dict) and _is_dataclass_type(arg) else len(errors), str(exc))
        raise ConfigError(errors[0] if errors else f"`{where}` has an invalid value {value!r}.")
    if origin is typing.Literal:
        if value not in args:
            allowed = ", ".join(repr(a) for a in args)
            raise ConfigError(f"`{where}` must be one of {allowed} (got {value!r}).")
        return value
    if origin in (tuple, list):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"`{where}` must be a list (got {value!r}).")
        item_tp = args[0] if args else Any
        items = [_coerce(item_tp, v, f"{where}[{i}]") for i, v in enumerate(value)]
        return tuple(items) if origin is tuple else items
    if origin is dict:
        if not isinstance(value, dict):
            raise ConfigError(f"`{where}` must be a mapping (got {value!r}).")
        return dict(value)
    if tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"`{where}` must be a number (got {value!r}).")
        if value != value:  # NaN: a number no setting can mean
            raise ConfigError(f"`{where}` must be a number (got .nan).")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            if isinstance(value, float) and value.is_integer():
                return int(value)
            raise ConfigError(f"`{where}` must be an integer (got {value!r}).")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"`{where}` must be true or false (got {value!r}).")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"`{where}` must be a string (got {value!r}).")
        return value
    return value


def from_dict(cls: type[T], data: dict[str, Any], prefix: str = "") -> T:
    """Build dataclass ``cls`` from ``data``; unknown keys are a :class:`ConfigError` (one that names a key in
    ``cls.REMOVED``, a mapping key → (value, note) of removed options, says it was removed).  A class whose checks
    name their keys from a fixed place (``cls.KEY``, e.g. ``model``) has that place renamed ``prefix`` in its errors."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise ConfigError(f"`{prefix or cls.__name__}` must be a mapping (got {data!r}).")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}  # type: ignore[arg-type]  # cls is a dataclass
    unknown = sorted(set(data) - set(fields))
    removed: dict[str, tuple[Any, str]] = getattr(cls, "REMOVED", {})
    for key in unknown:
        if key in removed:
            raise ConfigError(f"`{f'{prefix}.{key}' if prefix else key}` was removed ({removed[key][1]}); drop it.")
    if unknown:
        where = f"`{prefix}`" if prefix else cls.__name__
        raise ConfigError(
            f"unknown key(s) {', '.join(repr(k) for k in unknown)} in {where}; valid keys: {', '.join(sorted(fields))}."
        )
    required = [
        name
        for name, f in fields.items()
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING and name not in data
    ]
    if required:
        where = f"`{prefix}`" if prefix else cls.__name__
        raise ConfigError(
            f"{where} is missing required key(s) {', '.join(repr(k) for k in required)}; "
            f"give {', '.join(required)} (valid keys: {', '.join(sorted(fields))})."
        )
    kwargs = {name: _coerce(hints[name], value, f"{prefix}.{name}" if prefix else name) for name, value in data.items()}
    home = getattr(cls, "KEY", "")
    try:
        return cls(**kwargs)
    except ConfigError as exc:  # its checks name its keys from where it usually sits (``KEY``); say where it is
        if not home or not prefix or prefix == home or f"`{home}." not in str(exc):
            raise
        raise ConfigError(str(exc).replace(f"`{home}.", f"`{prefix}.", 1)) from None


def to_dict(obj: Any) -> Any:
    """Plain-Python (YAML-safe) form of a config dataclass."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (list, tuple)):
        return [to_dict(v) for v in obj]
    if isinstance(obj, dict):
        return {k: to_dict(v) for k, v in obj.items()}
    return obj


YAML_MAX_NODES = 1_000_000
"""The most values a YAML document may expand to, aliases counted each time they are used (a "billion
laughs" document — aliases of aliases — is refused before it is built)."""

MAX_FILE_BYTES = {"YAML file": 16 * 2**20, "file": 4 * 2**30}
"""Largest file [bytes] read per kind (``what`` of :func:`read_file_bytes`); ``RFLSCM_MAX_FILE_BYTES`` in the
environment raises (or lowers) every limit at once."""


class StrictLoader(yaml.SafeLoader):
    """PyYAML's safe loader that refuses a key given twice in one mapping (PyYAML keeps the last silently) and a
    document whose aliases expand to more than :data:`YAML_MAX_NODES` values; merge keys (``<<: *base``) work."""

    def construct_document(self, node: yaml.Node) -> Any:
        expanded_size(node, YAML_MAX_NODES)
        return super().construct_document(node)

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: dict[Any, int] = {}
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue  # `<<: *base` — merged keys may be overridden by the mapping's own
            key = self.construct_object(key_node, deep=True)
            try:
                hash(key)
            except TypeError:
                line = key_node.start_mark.line + 1
                raise ConfigError(f"line {line}: a key must be a plain value (got {key!r}).") from None
            if key in seen:
                raise ConfigError(
                    f"line {key_node.start_mark.line + 1}: key {key!r} appears twice in the same mapping "
                    f"(first on line {seen[key]}); keep one."
                )
            seen[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep=deep)


def expanded_size(root: yaml.Node, limit: int) -> int:
    """The number of values ``root`` stands for once every alias is expanded; more than ``limit`` (or an alias
    that contains itself) is a :class:`ConfigError`.  Linear in the number of distinct nodes."""
    sizes: dict[int, int] = {}
    active: set[int] = set()

    def size(node: yaml.Node) -> int:
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in active:
            raise ConfigError(f"line {node.start_mark.line + 1}: an alias refers to a value that contains it.")
        active.add(key)
        total = 1
        if isinstance(node, yaml.SequenceNode):
            total += sum(size(child) for child in node.value)
        elif isinstance(node, yaml.MappingNode):
            total += sum(size(k) + size(v) for k, v in node.value)
        active.discard(key)
        if total > limit:
            raise ConfigError(
                f"line {node.start_mark.line + 1}: the document expands to more than {limit:,} values "
                "(aliases of aliases?); expand fewer aliases."
            )
        sizes[key] = total
        return total

    try:
        return size(root)
    except RecursionError:
        raise ConfigError("the document nests too deeply to be read.") from None


def parse_yaml(text: str) -> Any:
    """YAML text → Python values, with :class:`StrictLoader` (safe tags only, no duplicate keys, a bounded
    alias expansion)."""
    return yaml.load(text, Loader=StrictLoader)


def max_file_bytes(what: str) -> int:
    """The size limit [bytes] of a file kind (:data:`MAX_FILE_BYTES`, ``$RFLSCM_MAX_FILE_BYTES`` overrides)."""
    raw = os.environ.get("RFLSCM_MAX_FILE_BYTES", "").strip()
    if raw:
        try:
            return int(float(raw))
        except (ValueError, OverflowError):
            raise ConfigError(f"RFLSCM_MAX_FILE_BYTES must be a number of bytes (got {raw!r}).") from None
    return MAX_FILE_BYTES.get(what, MAX_FILE_BYTES["file"])


def regular_file_size(path: str | Path, what: str = "file", error: type[RflscmError] = ConfigError) -> int:
    """``os.stat`` of ``path`` (symlinks followed) without opening it: a missing file, a folder, a FIFO, a device
    or a file above its kind's size limit raises ``error`` in one line.  Returns the size [bytes]."""
    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise error(f"{path}: {what} not found.") from None
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({exc.strerror or type(exc).__name__}).") from None
    if stat.S_ISDIR(st.st_mode):
        raise error(f"{path}: is a folder, not a {what}; give the {what} itself.")
    if not stat.S_ISREG(st.st_mode):
        raise error(f"{path}: is not a regular file (a pipe, a device or a socket); give the {what} itself.")
    limit = max_file_bytes(what)
    if st.st_size > limit:
        raise error(
            f"{path}: {st.st_size:,} bytes, above the {limit:,}-byte limit for a {what} "
            "(set RFLSCM_MAX_FILE_BYTES to raise it)."
        )
    return int(st.st_size)


def read_file_bytes(path: str | Path, what: str = "file", error: type[RflscmError] = ConfigError) -> bytes:
    """The bytes of ``path``; a missing file, a folder, a special file (FIFO, device), a file above its size
    limit or an unreadable file raises ``error`` in one line.  Never opens anything but a regular file."""
    path = Path(path)
    size = regular_file_size(path, what, error)
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))  # never blocks, even if swapped for a FIFO
        with os.fdopen(fd, "rb") as f:
            if not stat.S_ISREG(os.fstat(f.fileno()).st_mode):
                raise error(f"{path}: is not a regular file (a pipe, a device or a socket); give the {what} itself.")
            data = f.read(size + 1)
    except PermissionError:
        raise error(f"{path}: cannot read the {what} (permission denied); make it readable.") from None
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({exc.strerror or type(exc).__name__}).") from None
    if len(data) > size:
        raise error(f"{path}: the {what} grew while it was read; read it again when it is complete.")
    return data


def read_text_file(path: str | Path, what: str = "file") -> str:
    """UTF-8 text of a file; a missing file, a folder, no permission or another encoding is a :class:`ConfigError`."""
    data = read_file_bytes(path, what)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        raise ConfigError(
            f"{path} line {line}: byte 0x{data[exc.start]:02x} is not UTF-8 text; save the file as UTF-8."
        ) from None
    if "\x00" in text:
        raise ConfigError(f"{path}: holds NUL bytes; this is not a text file.")
    return text


def load_yaml(path: str | Path) -> dict[str, Any]:
    """Read a YAML mapping, turning I/O, encoding and syntax problems and duplicate keys into :class:`ConfigError`."""
    path = Path(path)
    text = read_text_file(path, "YAML file")
    try:
        data = parse_yaml(text)
    except ConfigError as exc:
        raise ConfigError(f"{path} {exc}") from None
    except yaml.YAMLError as exc:
        raise ConfigError(f"{path}: not valid YAML ({exc}).") from None
    except (ValueError, TypeError, OverflowError, RecursionError) as exc:  # e.g. a timestamp out of range
        raise ConfigError(f"{path}: a value cannot be read ({exc}).") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ConfigError(f"{path}: the top level must be a mapping of keys to values.")
    return data


def load_config(cls: type[T], path: str | Path) -> T:
    """Load dataclass ``cls`` from a YAML file with strict keys."""
    data = load_yaml(path)
    try:
        return from_dict(cls, data)
    except ConfigError as exc:
        raise ConfigError(f"{path}: {exc}") from None


# --- overrides: a preset, then a user's YAML, then `--set section.key=value` --------------------------------------


def merge_config(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``over`` laid on top, mapping by mapping (a key of ``over`` replaces only that key)."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge_config(out[key], value)
        else:
            out[key] = value
    return out


def parse_set(item: str, option: str = "--set") -> tuple[list[str], Any]:
    """``"train.steps=500"`` → ``(["train", "steps"], 500)``: the value is read as a YAML scalar or flow value
    (``true``, ``null``, ``1e-3``, ``[1, 2]``, ``{a: 1}``); a missing ``=`` or an empty key is a :class:`ConfigError`."""
    key, sep, text = item.partition("=")
    path = [p.strip() for p in key.split(".")]
    if not sep or not all(path):
        raise ConfigError(f"{option} {item!r}: write SECTION.KEY=VALUE, e.g. {option} train.steps=500.")
    try:
        value = parse_yaml(text) if text.strip() else ""
    except (yaml.YAMLError, ConfigError):
        value = text
    return path, value


def _scalar_for(tp: Any, value: Any) -> Any:
    """A YAML string that the field's type reads as a number (YAML 1.1 takes ``1e-3`` for text)."""
    if not isinstance(value, str):
        return value
    options = typing.get_args(tp) if typing.get_origin(tp) in (typing.Union, types.UnionType) else (tp,)
    for option in options:
        try:
            if option is float:
                return float(value)
            if option is int:
                return int(value)
        except ValueError:
            continue
    return value


def _section_of(tp: Any) -> Any:
    """The dataclass of a field typed ``X | Dataclass`` (a switch that may also carry settings, e.g. ``bool |
    WNOMPConfig``), so that ``--set`` reaches into it; any other type unchanged."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        sections = [arg for arg in typing.get_args(tp) if _is_dataclass_type(arg)]
        if len(sections) == 1:
            return sections[0]
    return tp


def apply_sets(
    cls: type, data: dict[str, Any], items: list[str] | tuple[str, ...], option: str = "--set"
) -> dict[str, Any]:
    """``data`` (a mapping for dataclass ``cls``) with each ``SECTION.KEY=VALUE`` of ``items`` set in it.

    Every key on the path must be a field of the dataclass at that level (a mapping-typed field takes any
    key below it); the value is checked against the field's type.  Errors name the item and list the valid
    keys.
    """
    out = merge_config({}, data)
    for item in items:
        path, value = parse_set(item, option)
        tp: Any = cls
        node = out
        for depth, key in enumerate(path):
            where = ".".join(path[: depth + 1])
            tp = _section_of(tp)
            if _is_dataclass_type(tp):
                hints = typing.get_type_hints(tp)
                fields = sorted(f.name for f in dataclasses.fields(tp) if f.init)
                if key not in fields:
                    section = f"`{'.'.join(path[:depth])}`" if depth else "the top level"
                    raise ConfigError(
                        f"{option} {item}: unknown key `{key}` in {section}; valid keys: {', '.join(fields)}."
                    )
                tp = hints[key]
            elif typing.get_origin(tp) is dict or (isinstance(node, dict) and tp is Any):
                tp = (typing.get_args(tp) or (Any, Any))[1]
            else:
                raise ConfigError(f"{option} {item}: `{'.'.join(path[:depth])}` is a value, not a section.")
            if depth == len(path) - 1:
                value = _scalar_for(tp, value)
                try:
                    _coerce(tp, value, where)
                except ConfigError as exc:
                    raise ConfigError(f"{option} {item}: {exc}") from None
                node[key] = value
            else:
                child = node.get(key)
                node[key] = child = dict(child) if isinstance(child, dict) else {}
                node = child
    return out
