"""Readers for file codebooks: explicit element weights and measured per-beam gain tables.

Layouts (docs/codebooks.md):

- weights ``.npy``: complex ``[num_beams, num_h, num_v]``;
  weights CSV/Parquet: columns ``beam_id, element_h, element_v, re, im`` (one row per beam and element,
  ids from 0, every (beam, element) once).
- pattern CSV/Parquet: columns ``beam_id, azimuth_deg, elevation_deg, gain_dbi`` on a full grid
  (every beam at every azimuth × elevation once), antenna frame, azimuth in [−180, 180).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from rflscm.errors import DataError

WEIGHT_COLUMNS = ("beam_id", "element_h", "element_v", "re", "im")
PATTERN_COLUMNS = ("beam_id", "azimuth_deg", "elevation_deg", "gain_dbi")


def resolve_inside(root: Path, name: str, key: str) -> Path:
    """``root / name``, refused when it leaves the scenario folder or does not exist."""
    base = Path(root).resolve()
    path = (base / name).resolve()
    if not path.is_relative_to(base):
        raise DataError(f"`{key}` = {name!r} lies outside the scenario folder ({base}); give a path inside it.")
    if not path.is_file():
        raise DataError(f"`{key}` = {name!r}: file not found ({path}); names are relative to the scenario folder.")
    return path


def _table(path: Path, columns: tuple[str, ...]) -> pd.DataFrame:
    try:
        df = pd.read_parquet(path) if path.suffix.lower() in (".parquet", ".pq") else pd.read_csv(path)
    except (OSError, ValueError) as exc:
        raise DataError(f"{path.name}: cannot read the table ({' '.join(str(exc).split())}).") from None
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise DataError(f"{path.name}: missing column(s) {', '.join(missing)}; needs {', '.join(columns)}.")
    out = df[list(columns)].apply(pd.to_numeric, errors="coerce")
    bad = ~np.isfinite(out.to_numpy(dtype=np.float64)).all(axis=1)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise DataError(
            f"{path.name} row {row + 2}: a value is missing or not a finite number ({df.iloc[row].to_dict()})."
        )
    if out.empty:
        raise DataError(f"{path.name}: the table has no rows.")
    return out


def _ids(values: np.ndarray, path: Path, column: str) -> np.ndarray:
    if (values != np.round(values)).any() or (values < 0).any():
        raise DataError(f"{path.name}: `{column}` must be whole numbers from 0.")
    return values.astype(np.int64)


def read_weights_file(path: Path) -> np.ndarray:
    """Complex weights ``[num_beams, num_h, num_v]`` normalised to unit power per beam."""
    if path.suffix.lower() == ".npy":
        try:
            w = np.load(path, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise DataError(f"{path.name}: cannot read the .npy file ({' '.join(str(exc).split())}).") from None
        if w.ndim != 3 or not (np.iscomplexobj(w) or np.issubdtype(w.dtype, np.number)):
            raise DataError(f"{path.name}: needs a numeric array [num_beams, num_h, num_v] (got shape {w.shape}).")
        w = w.astype(np.complex128)
    else:
        df = _table(path, WEIGHT_COLUMNS)
        b = _ids(df["beam_id"].to_numpy(np.float64), path, "beam_id")
        h = _ids(df["element_h"].to_numpy(np.float64), path, "element_h")
        v = _ids(df["element_v"].to_numpy(np.float64), path, "element_v")
        shape = (int(b.max()) + 1, int(h.max()) + 1, int(v.max()) + 1)
        if len(df) != int(np.prod(shape)) or len(set(zip(b, h, v, strict=True))) != len(df):
            raise DataError(
                f"{path.name}: needs every (beam_id, element_h, element_v) of {shape[0]} × {shape[1]} × {shape[2]} "
                f"exactly once (got {len(df)} rows)."
            )
        w = np.zeros(shape, np.complex128)
        w[b, h, v] = df["re"].to_numpy(np.float64) + 1j * df["im"].to_numpy(np.float64)
    if not np.isfinite(w).all():
        raise DataError(f"{path.name}: the weights must be finite numbers.")
    power = (np.abs(w) ** 2).sum(axis=(1, 2))
    if (power <= 0).any():
        raise DataError(f"{path.name}: beam {int(np.flatnonzero(power <= 0)[0])} has all-zero weights.")
    return w / np.sqrt(power)[:, None, None]


def read_pattern_table(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sorted azimuths [deg], elevations [deg] and gains [dBi] ``[num_beams, n_el, n_az]``."""
    df = _table(path, PATTERN_COLUMNS)
    b = _ids(df["beam_id"].to_numpy(np.float64), path, "beam_id")
    az = df["azimuth_deg"].to_numpy(np.float64)
    el = df["elevation_deg"].to_numpy(np.float64)
    if (az < -180).any() or (az >= 180).any():
        raise DataError(f"{path.name}: `azimuth_deg` must lie in −180…<180° (antenna frame, positive to the left).")
    if (np.abs(el) > 90).any():
        raise DataError(f"{path.name}: `elevation_deg` must lie in −90…90° (antenna frame, positive up).")
    gain = df["gain_dbi"].to_numpy(np.float64)
    if (gain > 60).any():
        raise DataError(f"{path.name}: `gain_dbi` = {gain.max():g} dBi is implausible (above 60 dBi).")
    az_u, ia = np.unique(az, return_inverse=True)
    el_u, ie = np.unique(el, return_inverse=True)
    beams = int(b.max()) + 1
    if len(df) != beams * len(az_u) * len(el_u) or len(set(zip(b, ia, ie, strict=True))) != len(df):
        raise DataError(
            f"{path.name}: needs every beam_id 0…{beams - 1} at every azimuth × elevation of the grid "
            f"({len(az_u)} × {len(el_u)}) exactly once (got {len(df)} rows)."
        )
    if len(az_u) < 2:
        raise DataError(f"{path.name}: needs at least two azimuths.")
    out = np.zeros((beams, len(el_u), len(az_u)))
    out[b, ie, ia] = gain
    return az_u, el_u, out
