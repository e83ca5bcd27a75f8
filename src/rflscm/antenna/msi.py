"""Reader for Planet/MSI antenna pattern files (``.msi``, ``.pln``, ``.txt``).

The format is line based: keyword lines (``NAME``, ``FREQUENCY``, ``GAIN <v> [dBi|dBd]``,
``TILT``, ``COMMENT`` …) followed by two blocks, ``HORIZONTAL <n>`` and
``VERTICAL <n>``, each of ``n`` lines ``<angle_deg> <loss_db>``.  Angles must be
evenly spaced from 0; losses are attenuation relative to the peak (≥ 0).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rflscm.antenna.element import MeasuredElement
from rflscm.errors import DataError

_DBD_TO_DBI = 2.15


def _parse_gain(tokens: list[str], where: str) -> float:
    try:
        value = float(tokens[1])
        if not -20.0 <= value <= 50.0:  # also refuses nan and inf
            raise ValueError
    except (IndexError, ValueError):
        raise DataError(
            f"{where}: GAIN needs a number in −20…50 dBi, e.g. `GAIN 17.5 dBi` (got {' '.join(tokens)!r})."
        ) from None
    unit = tokens[2].lower() if len(tokens) > 2 else "dbi"
    if unit not in ("dbi", "dbd"):
        raise DataError(f"{where}: GAIN unit must be dBi or dBd (got {tokens[2]!r}).")
    return value + (_DBD_TO_DBI if unit == "dbd" else 0.0)


def _parse_frequency(tokens: list[str], where: str) -> float:
    """``FREQUENCY <MHz>`` (Planet's unit; an optional unit token MHz/GHz/Hz is honoured) → Hz."""
    scale = {"hz": 1.0, "khz": 1e3, "mhz": 1e6, "ghz": 1e9}
    try:
        value = float(tokens[1])
        unit = tokens[2].lower() if len(tokens) > 2 else "mhz"
        hz = value * scale[unit]
        if not 1e6 <= hz <= 1e12:  # also refuses nan and inf
            raise ValueError
    except (IndexError, ValueError, KeyError):
        raise DataError(
            f"{where}: FREQUENCY needs the carrier in MHz, e.g. `FREQUENCY 3500` (got {' '.join(tokens)!r})."
        ) from None
    return hz


def _read_block(lines: list[str], start: int, count: int, label: str, path: Path) -> np.ndarray:
    if start + count > len(lines):
        raise DataError(
            f"{path} line {start}: {label} announces {count} rows but the file ends after {len(lines) - start}."
        )
    rows = np.empty((count, 2))
    for k in range(count):
        lineno = start + k + 1
        parts = lines[start + k].split()
        try:
            rows[k] = [float(parts[0]), float(parts[1])]
        except (IndexError, ValueError):
            raise DataError(
                f"{path} line {lineno}: expected `<angle_deg> <loss_db>` in the {label} block "
                f"(got {lines[start + k].strip()!r})."
            ) from None
    if not np.isfinite(rows).all():
        bad = int(np.flatnonzero(~np.isfinite(rows).all(axis=1))[0])
        raise DataError(f"{path} line {start + bad + 1}: {label} row holds a value that is not a finite number.")
    expected = np.arange(count) * (360.0 / count)
    if not np.allclose(rows[:, 0], expected, atol=1e-6):
        bad = int(np.argmax(~np.isclose(rows[:, 0], expected, atol=1e-6)))
        raise DataError(
            f"{path} line {start + bad + 1}: {label} angles must run 0…360 in equal steps of {360.0 / count:g}° "
            f"(got {rows[bad, 0]:g}°, expected {expected[bad]:g}°)."
        )
    if np.any(rows[:, 1] < 0):
        bad = int(np.argmax(rows[:, 1] < 0))
        raise DataError(
            f"{path} line {start + bad + 1}: {label} losses must be ≥ 0 dB below the peak (got {rows[bad, 1]:g})."
        )
    return rows[:, 1]


def read_msi(path: str | Path) -> MeasuredElement:
    """Read a Planet/MSI pattern file into a :class:`MeasuredElement`."""
    path = Path(path)
    if path.is_dir():
        raise DataError(f"{path}: is a folder, not an antenna pattern file.")
    if not path.is_file():
        raise DataError(f"{path}: antenna pattern file not found.")
    try:
        lines = path.read_bytes().decode("utf-8", errors="replace").splitlines()  # comments may be in any encoding
    except OSError as exc:
        raise DataError(
            f"{path}: cannot read the antenna pattern file ({exc.strerror or type(exc).__name__})."
        ) from None
    name, gain, freq = path.stem, None, None
    blocks: dict[str, np.ndarray] = {}
    i = 0
    while i < len(lines):
        tokens = lines[i].split()
        key = tokens[0].upper() if tokens else ""
        if key == "NAME" and len(tokens) > 1:
            name = " ".join(tokens[1:])
        elif key == "FREQUENCY":
            freq = _parse_frequency(tokens, f"{path} line {i + 1}")
        elif key == "GAIN":
            gain = _parse_gain(tokens, f"{path} line {i + 1}")
        elif key in ("HORIZONTAL", "VERTICAL"):
            try:
                count = int(tokens[1])
            except (IndexError, ValueError):
                raise DataError(
                    f"{path} line {i + 1}: `{key}` must be followed by the number of rows, e.g. `{key} 360`."
                ) from None
            if count < 2:
                raise DataError(f"{path} line {i + 1}: `{key}` needs at least 2 rows (got {count}).")
            blocks[key] = _read_block(lines, i + 1, count, key, path)
            i += count
        i += 1
    missing = [k for k in ("HORIZONTAL", "VERTICAL") if k not in blocks]
    if missing:
        raise DataError(f"{path}: no {' and no '.join(missing)} block found; an MSI file needs both.")
    if gain is None:
        raise DataError(f"{path}: no GAIN line found (e.g. `GAIN 17.5 dBi`).")
    return MeasuredElement(
        max_gain_dbi=gain,
        horizontal_loss_db=tuple(float(v) for v in blocks["HORIZONTAL"]),
        vertical_loss_db=tuple(float(v) for v in blocks["VERTICAL"]),
        name=name,
        frequency_hz=freq,
    )


def write_msi(element: MeasuredElement, path: str | Path, frequency_mhz: float | None = None) -> None:
    """Write ``element`` as a Planet/MSI file (the inverse of :func:`read_msi`)."""
    out = [f"NAME {element.name}"]
    if frequency_mhz is None and element.frequency_hz is not None:
        frequency_mhz = element.frequency_hz / 1e6
    if frequency_mhz is not None:
        out.append(f"FREQUENCY {frequency_mhz:g}")
    out.append(f"GAIN {element.max_gain_dbi:.2f} dBi")
    for label, table in (("HORIZONTAL", element.horizontal_loss_db), ("VERTICAL", element.vertical_loss_db)):
        n = len(table)
        out.append(f"{label} {n}")
        out.extend(f"{k * 360.0 / n:g} {v:.2f}" for k, v in enumerate(table))
    Path(path).write_text("\n".join(out) + "\n")


def sample_msi_path() -> Path:
    """Path of the sample pattern shipped with rflscm: a 65° × 7°, 17.5 dBi panel at 3.5 GHz
    (3GPP-style parabolic cuts, 30 dB front-back) — a format example, not a vendor antenna."""
    from importlib.resources import files

    return Path(str(files("rflscm") / "assets" / "antennas" / "sample_65deg_3500MHz.msi"))


def patch_msi_path() -> Path:
    """Path of the second shipped pattern: a synthesised embedded patch element of a 3.5 GHz panel (90° × 70°
    HPBW, 7 dBi, 25 dB front-back, edge ripple; ``scripts/make_patch_element.py``), for the field regime's
    real antenna (``field_model.real_element``) — realistic traits, not a vendor measurement."""
    from importlib.resources import files

    return Path(str(files("rflscm") / "assets" / "antennas" / "patch_90x70deg_3500MHz.msi"))
