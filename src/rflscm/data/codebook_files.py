"""Codebooks that live in files beside ``scenario.yaml``: vendors' explicit per-beam element weights.

A ``type: weights`` codebook names a table (CSV or Parquet) with one row per (beam, element)::

    beam_id, element_h, element_v, re, im

``beam_id`` 0…B−1, ``element_h`` 0…N_h−1 along the array's horizontal axis and ``element_v`` 0…N_v−1 along its
vertical axis (the same element order as the cells tables' ``array_nh`` × ``array_nv``), ``re``/``im`` the
complex weight.  Every (beam, element) appears once; a beam is normalised to unit power when read.  A ``.npy``
file holding a complex array ``[beams, num_h, num_v]`` is accepted too (read without pickle).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pandas as pd

from rflscm.antenna.codebook import Codebook, WeightsCodebook
from rflscm.data.columns import TableRef, duplicate_rows, float_column, int_column, raise_rows, require_columns
from rflscm.data.io import LINE_NUMBERS, read_bytes, read_table, table_kind
from rflscm.errors import ConfigError, DataError

WEIGHT_COLUMNS = ["beam_id", "element_h", "element_v", "re", "im"]
MAX_WEIGHT_BEAMS = 4096
"""Most beams of one weights codebook (massive-MIMO CSI-RS sets have a few hundred)."""
MAX_WEIGHT_ELEMENTS = 4096
"""Most elements per beam (the cells tables' limit on array_nh × array_nv)."""


def bind_codebook_files(codebooks: dict[str, Codebook], root: Path | None, where: str) -> dict[str, Codebook]:
    """``codebooks`` with every ``type: weights`` codebook's file read from folder ``root``."""
    out: dict[str, Codebook] = {}
    for name, book in codebooks.items():
        if isinstance(book, WeightsCodebook):
            if root is None:
                raise ConfigError(f"{where}: `codebooks.{name}` reads `{book.file}`, which needs the scenario folder.")
            book = read_weights_codebook(root, book, f"{where}: `codebooks.{name}.file`")
        out[name] = book
    return out


def read_weights_codebook(root: Path, book: WeightsCodebook, where: str) -> WeightsCodebook:
    """Read ``book.file`` (relative to ``root``, inside it) and return the bound codebook."""
    rel = Path(book.file)
    path = (root / rel).resolve()
    if rel.is_absolute() or not path.is_relative_to(root.resolve()):
        raise DataError(f"{where} = {book.file!r} lies outside the scenario folder; copy the file into it.")
    if not path.is_file():
        raise DataError(f"{where} = {book.file!r}: no such file ({path}); paths are relative to the scenario folder.")
    digest = hashlib.sha256(read_bytes(path, "codebook file")).hexdigest()
    if book.sha256 and book.sha256 != digest:
        raise DataError(
            f"{where} = {book.file!r}: the file's SHA-256 {digest[:12]}… differs from the `sha256` in scenario.yaml "
            f"({book.sha256[:12]}…); the weights changed since the scenario was written."
        )
    values = _read_npy(path, book.file) if path.suffix.lower() == ".npy" else _read_table(path, book.file)
    try:
        return WeightsCodebook.of(values, book.file, digest)
    except ConfigError as exc:
        raise DataError(f"{where}: {exc}") from None


def _read_npy(path: Path, name: str) -> np.ndarray:
    try:
        values = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise DataError(f"{name}: not a readable .npy array of complex weights ({exc}).") from None
    if values.ndim != 3 or values.size > MAX_WEIGHT_BEAMS * MAX_WEIGHT_ELEMENTS:
        raise DataError(f"{name}: a .npy weights file holds [beams, num_h, num_v] (got shape {list(values.shape)}).")
    if values.dtype.kind not in "fc":
        raise DataError(f"{name}: weights must be complex or real numbers (got dtype {values.dtype}).")
    return values


def _read_table(path: Path, name: str) -> np.ndarray:
    df = read_table(path)  # refuses an unknown extension in one line
    ref = TableRef(name, csv=table_kind(path) == "csv", lines=df.attrs.get(LINE_NUMBERS))
    require_columns(df, ref, WEIGHT_COLUMNS)
    index = {c: int_column(df, ref, c) for c in ("beam_id", "element_h", "element_v")}
    for column, values in index.items():
        raise_rows(ref, values < 0, column, df[column], "must be ≥ 0 (indices count from 0)")
    beams, nh, nv = (int(index[c].max()) + 1 for c in ("beam_id", "element_h", "element_v"))
    if beams > MAX_WEIGHT_BEAMS or nh * nv > MAX_WEIGHT_ELEMENTS:
        raise DataError(
            f"{name}: {beams} beams of {nh} × {nv} elements exceed the limits ({MAX_WEIGHT_BEAMS} beams, "
            f"{MAX_WEIGHT_ELEMENTS} elements)."
        )
    keys = index["beam_id"] * nh * nv + index["element_h"] * nv + index["element_v"]
    duplicate_rows(ref, df, ["beam_id", "element_h", "element_v"], "give each (beam, element) once", packed=keys)
    if len(keys) != beams * nh * nv:
        raise DataError(
            f"{name}: {len(keys)} rows for {beams} beams × {nh} × {nv} elements; every (beam, element) needs one row."
        )
    w = np.zeros(beams * nh * nv, dtype=np.complex128)
    w[keys] = float_column(df, ref, "re") + 1j * float_column(df, ref, "im")
    return w.reshape(beams, nh, nv)


def weights_table(book: WeightsCodebook) -> pd.DataFrame:
    """The codebook's unit-power weights as a ``beam_id, element_h, element_v, re, im`` table (the file layout)."""
    b, h, v = np.meshgrid(*(np.arange(n) for n in book.values.shape), indexing="ij")
    w = book.values.ravel()
    return pd.DataFrame(
        {"beam_id": b.ravel(), "element_h": h.ravel(), "element_v": v.ravel(), "re": w.real, "im": w.imag}
    )
