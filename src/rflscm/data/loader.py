"""Loading and saving scenario folders (``scenario.yaml`` + tables + point cloud).

:func:`load_scenario` validates everything and raises one-line
:class:`~rflscm.errors.DataError` / :class:`~rflscm.errors.ConfigError`
messages; :func:`save_scenario` writes normalised tables, so that
``load_scenario(save_scenario(s, dir)) == s``.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import yaml

from rflscm.config import load_yaml, regular_file_size
from rflscm.data.cells import DEFAULT_ELEMENT, normalise_cells
from rflscm.data.columns import TableRef
from rflscm.data.io import LINE_NUMBERS, read_table, table_kind, write_table
from rflscm.data.measurements import empty_measurements, normalise_measurements
from rflscm.data.meta import ScenarioMeta, meta_from_dict
from rflscm.data.plausibility import UE_KINDS, check_grid_heights, check_overlap
from rflscm.data.pointcloud import read_point_cloud, write_point_cloud
from rflscm.data.positions import XYZ, normalise_grids
from rflscm.data.safe_io import write_text_atomic
from rflscm.data.scenario import Scenario
from rflscm.errors import ConfigError, DataError

SCENARIO_FILE = "scenario.yaml"
TABLE_FORMATS = {"parquet": ".parquet", "csv": ".csv"}


def locate_scenario(path: str | Path) -> tuple[Path, Path]:
    """``(folder, yaml file)`` of a scenario given as its folder or its YAML file."""
    path = Path(path).expanduser()
    if path.is_dir():
        yaml_path = path / SCENARIO_FILE
        if not yaml_path.is_file():
            raise DataError(
                f"{path}: no {SCENARIO_FILE} in this folder; a scenario is a folder with {SCENARIO_FILE} "
                "(name, frequencies_hz, codebooks, rounds, grids, measurements) next to its tables."
            )
        return path.resolve(), yaml_path
    if path.is_file():
        if path.suffix.lower() not in (".yaml", ".yml"):
            raise DataError(f"{path}: not a scenario; give the scenario folder or its {SCENARIO_FILE}.")
        return path.parent.resolve(), path
    raise DataError(f"{path}: no such scenario folder or file.")


ALLOW_OUTSIDE = "allow_outside"
"""``scenario.yaml`` key: ``true`` lets file names point outside the scenario folder (absolute, ``..``, symlinks)."""

MAX_BEAMS = 4096
"""The most beams one codebook may declare (5G NR: at most 64 SSB beams; a 32-port DFT codebook with 4×4
oversampling has 512)."""


def _read_meta_dict(yaml_path: Path) -> dict[str, Any]:
    try:
        data = load_yaml(yaml_path)
    except ConfigError as exc:  # YAML syntax errors span several lines: keep the CLI's one line
        raise ConfigError(" ".join(str(exc).split())) from None
    if not data:
        raise ConfigError(f"{yaml_path.name} is empty; it needs name, frequencies_hz, codebooks, rounds and grids.")
    return data


def load_meta(yaml_path: Path) -> ScenarioMeta:
    """Read and validate ``scenario.yaml`` (``allow_outside`` is read by :func:`allows_outside`)."""
    data = _read_meta_dict(yaml_path)
    allows_outside(data, yaml_path.name)
    ue_kind(data, yaml_path.name)
    data.pop(ALLOW_OUTSIDE, None)
    data.pop(UE_KEY, None)
    check_declared_beams(data.get("codebooks"), yaml_path.name)
    return meta_from_dict(data, where=yaml_path.name, root=yaml_path.parent)


UE_KEY = "ue"
"""``scenario.yaml`` key: ``ground`` (default) or ``aerial``: which grid heights are plausible."""


def ue_kind(data: dict[str, Any], yaml_name: str) -> str:
    value = data.get(UE_KEY, "ground")
    if value not in UE_KINDS:
        raise ConfigError(f"{yaml_name}: `{UE_KEY}` must be one of {', '.join(UE_KINDS)} (got {value!r}).")
    return str(value)


def allows_outside(data: dict[str, Any], yaml_name: str) -> bool:
    value = data.get(ALLOW_OUTSIDE, False)
    if not isinstance(value, bool):
        raise ConfigError(f"{yaml_name}: `{ALLOW_OUTSIDE}` must be true or false (got {value!r}).")
    return value


def check_declared_beams(codebooks: object, yaml_name: str) -> None:
    """Refuse a codebook declaring more than :data:`MAX_BEAMS` beams before it is built (its checks are quadratic)."""
    if not isinstance(codebooks, dict):
        return
    for name, spec in codebooks.items():
        if not isinstance(spec, dict):
            continue
        axes = [("azimuths_deg", "tilts_deg"), ("beams_h", "beams_v")]
        for a, b in axes:
            if a in spec or b in spec:
                na, nb = (len(spec[k]) if isinstance(spec.get(k), (list, tuple)) else 1 for k in (a, b))
                if na * nb > MAX_BEAMS:
                    raise ConfigError(
                        f"{yaml_name}: `codebooks.{name}` declares {na} × {nb} = {na * nb:,} beams, above the "
                        f"{MAX_BEAMS:,}-beam limit of a codebook."
                    )


def inside_scenario(root: Path, name: str, key: str, yaml_name: str, allow_outside: bool) -> Path:
    """``root / name`` once symlinks are resolved; a place outside the scenario folder is a :class:`DataError`
    unless the scenario says ``allow_outside: true``."""
    path = root / name
    if allow_outside:
        return path
    real, base = os.path.realpath(path), os.path.realpath(root)
    if real != base and not real.startswith(base.rstrip(os.sep) + os.sep):
        raise DataError(
            f"{yaml_name}: `{key}` = {name!r} resolves outside the scenario folder ({real}); keep the file inside "
            f"{base}, or add `{ALLOW_OUTSIDE}: true` to {yaml_name} to read it there."
        )
    return path


def scenario_inputs(path: str | Path) -> list[Path]:
    """Every file and folder a scenario's ``scenario.yaml`` names (itself included), for refusing an output
    that would overwrite one; a scenario that cannot be read yet gives what is known (loading reports it)."""
    path = Path(path).expanduser()
    try:
        root, yaml_path = locate_scenario(path)
        data = _read_meta_dict(yaml_path)
    except (ConfigError, DataError):
        return [path]
    names: list[object] = [data.get(k) for k in ("grids", "measurements", "point_cloud", "truth")]
    rounds = data.get("rounds")
    if isinstance(rounds, dict):
        names += [r.get("cells") if isinstance(r, dict) else r for r in rounds.values()]
    return [yaml_path, *(root / str(n) for n in names if isinstance(n, str) and n)]


def _referenced(root: Path, name: str, key: str, yaml_name: str, allow_outside: bool = False) -> Path:
    path = inside_scenario(root, name, key, yaml_name, allow_outside)
    if not path.exists():
        raise DataError(
            f"{yaml_name}: `{key}` = {name!r}: not found ({path}); file names are relative to the scenario folder."
        )
    if key != "truth" and path.is_dir():
        raise DataError(f"{yaml_name}: `{key}` = {name!r} is a folder ({path}); give the file itself.")
    if key == "truth" and not path.is_dir():
        raise DataError(f"{yaml_name}: `truth` = {name!r} is a file ({path}); give the truth folder.")
    return path


def _read(root: Path, name: str, key: str, yaml_name: str, outside: bool) -> tuple[pd.DataFrame, TableRef]:
    path = _referenced(root, name, key, yaml_name, outside)
    df = read_table(path)
    return df, TableRef(name, csv=table_kind(path) == "csv", lines=df.attrs.get(LINE_NUMBERS))


def load_scenario(path: str | Path, measurements: bool = True) -> Scenario:
    """Load and validate a scenario folder (or its YAML file); ``measurements=False`` leaves the measurements
    table unread (empty), for a step that only needs cells, grids and the point cloud (re-measuring a trace).

    Raises:
        ConfigError: scenario.yaml is malformed (unknown or missing keys, bad values).
        DataError: a referenced file is missing or a table / point cloud is invalid; the message
            names the file, the row and the column.
    """
    root, yaml_path = locate_scenario(path)
    meta = load_meta(yaml_path)
    yaml_name = yaml_path.name
    raw = _read_meta_dict(yaml_path)
    outside, ue = allows_outside(raw, yaml_name), ue_kind(raw, yaml_name)
    cells: dict[int, pd.DataFrame] = {}
    elements: dict[str, Any] = {}
    for rnd, name in meta.rounds.items():
        df, ref = _read(root, name, f"rounds.{rnd}.cells", yaml_name, outside)
        _check_elements(df, root, f"rounds.{rnd}.cells", yaml_name, outside)
        round1 = None if rnd == 1 else (cells[1], meta.rounds[1])
        cells[rnd], found = normalise_cells(df, ref, meta, root, round1)
        elements.update(found)
    df, ref = _read(root, meta.grids, "grids", yaml_name, outside)
    grids = normalise_grids(df, ref, meta.origin, meta.ground)
    if meta.measurements is None or not measurements:
        table = empty_measurements()
    else:
        df, ref = _read(root, meta.measurements, "measurements", yaml_name, outside)
        table = normalise_measurements(df, ref, meta, cells, grids["grid_id"].to_numpy(), meta.grids)
    point_cloud = None
    if meta.point_cloud is not None:
        pc_path = _referenced(root, meta.point_cloud, "point_cloud", yaml_name, outside)
        regular_file_size(pc_path, "point cloud file", DataError)
        point_cloud = read_point_cloud(pc_path)
    if meta.truth is not None:
        _referenced(root, meta.truth, "truth", yaml_name, outside)
    parts: list[tuple[Any, np.ndarray]] = [(meta.rounds[1], cells[1][list(XYZ)].to_numpy(np.float64))]
    parts.append((meta.grids, grids[list(XYZ)].to_numpy(np.float64)))
    if point_cloud is not None:
        parts.append((meta.point_cloud, point_cloud.xyz))
    check_overlap(parts)
    check_grid_heights(parts[1][1], [p[1] for p in parts[:1] + parts[2:]], ue, meta.grids)
    scenario = Scenario(root, meta, cells, grids, table, point_cloud)
    scenario._elements.update(elements)
    return scenario


def _check_elements(df: pd.DataFrame, root: Path, key: str, yaml_name: str, outside: bool) -> None:
    """Element pattern files named in a cells table: inside the scenario folder and regular files, before the
    cells module reads them."""
    if "element" not in df.columns:
        return
    for name in pd.unique(df["element"].dropna()):
        text = str(name).strip()
        if not text or text.lower() == DEFAULT_ELEMENT:
            continue
        path = inside_scenario(root, text, f"{key}: element", yaml_name, outside)
        if path.exists() and not path.is_dir():
            regular_file_size(path, "antenna pattern file", DataError)


def save_scenario(scenario: Scenario, root: str | Path, table_format: str = "parquet") -> Path:
    """Write ``scenario`` to folder ``root`` (created if needed) and return the folder.

    Tables are written as ``cells_round<R>``, ``grids`` and ``measurements`` with the extension of
    ``table_format`` (``parquet`` or ``csv``); the point cloud keeps its format (PLY by default);
    element pattern files and the truth folder are copied when ``root`` is a new place.
    """
    if table_format not in TABLE_FORMATS:
        raise ConfigError(f"table format must be one of {', '.join(TABLE_FORMATS)} (got {table_format!r}).")
    ext = TABLE_FORMATS[table_format]
    root = Path(root).expanduser()
    root.mkdir(parents=True, exist_ok=True)
    meta = scenario.meta
    rounds = {r: f"cells_round{r}{ext}" for r in scenario.cells}
    for r, name in rounds.items():
        write_table(scenario.cells[r], root / name)
    grids_name = f"grids{ext}"
    write_table(scenario.grids, root / grids_name)
    measurements_name = None
    if meta.measurements is not None or len(scenario.measurements):
        measurements_name = f"measurements{ext}"
        write_table(scenario.measurements, root / measurements_name)
    pc_name = None
    if scenario.point_cloud is not None:
        pc_name = meta.point_cloud or "point_cloud.ply"
        write_point_cloud(scenario.point_cloud, root / pc_name)
    _copy_elements(scenario, root)
    truth = _copy_truth(scenario, root)
    new_meta = dataclasses.replace(
        meta, rounds=rounds, grids=grids_name, measurements=measurements_name, point_cloud=pc_name, truth=truth
    )
    text = yaml.safe_dump(_plain(new_meta.to_dict()), sort_keys=False, allow_unicode=True, default_flow_style=None)
    write_text_atomic(root / SCENARIO_FILE, text, "scenario file")
    return root


def _copy_elements(scenario: Scenario, root: Path) -> None:
    """Copy MSI element files and codebook files (``type: weights``/``pattern``) into ``root`` (same relative paths)."""
    tables = [t for t in scenario.cells.values() if "element" in t.columns]
    names = {str(n) for table in tables for n in table["element"].dropna().unique()} - {DEFAULT_ELEMENT, ""}
    names |= {str(f) for book in scenario.meta.codebooks.values() if (f := getattr(book, "file", ""))}
    names |= {scenario.meta.terrain} if scenario.meta.terrain else set()
    for name in sorted(names):
        source, target = scenario.root / name, root / name
        if Path(name).is_absolute() or ".." in Path(name).parts or not source.is_file():
            continue  # left as a reference; loading the copy reports it if it is not reachable
        if not target.exists() or not target.samefile(source):
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)


def _copy_truth(scenario: Scenario, root: Path) -> str | None:
    name = scenario.meta.truth
    if name is None:
        return None
    source, target = scenario.root / name, root / name
    if source.is_dir() and not (target.exists() and target.resolve() == source.resolve()):
        shutil.copytree(source, target, dirs_exist_ok=True)
    return name if target.is_dir() else None  # never reference a folder that is not there


def _plain(value: Any) -> Any:
    """YAML-safe Python values (tuples → lists, numpy scalars/arrays → Python)."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value
