"""Beam codebooks: SSB wide beams and 3GPP Type I DFT (CSI-RS) beams.

A codebook turns into beam weights ``W[num_beams, num_h, num_v]`` (complex,
unit power per beam) for an array at a carrier.  Gain convention: the beam
power towards ω is |Σ_e a_e(ω) W_e|², so a beam steered to ω₀ has
W_e ∝ exp(−j 2π/λ ⟨r_e, ω₀⟩).  Electrical tilt is a common vertical phase
taper that steers every beam down by ``elec_tilt_deg``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from rflscm.antenna.array import ArrayGeometry
from rflscm.antenna.beamfile import read_pattern_table, read_weights_file, resolve_inside
from rflscm.config import from_dict
from rflscm.errors import ConfigError, DataError


@dataclass(frozen=True)
class SSBCodebook:
    """Wide SSB beams: a grid of steering directions formed by a centred sub-array.

    Beam order: tilt-major (for each tilt, every azimuth).  Angles are in the
    antenna frame: azimuth positive to the boresight's left (CCW seen from
    above), tilt positive down.  A smaller sub-array gives wider beams.
    """

    type: Literal["ssb"] = "ssb"
    azimuths_deg: tuple[float, ...] = (-45.0, -15.0, 15.0, 45.0)
    tilts_deg: tuple[float, ...] = (0.0, 10.0)
    active_h: int = 4
    active_v: int = 2

    def __post_init__(self) -> None:
        if not self.azimuths_deg or not self.tilts_deg:
            raise ConfigError("an SSB codebook needs at least one azimuth and one tilt (`azimuths_deg`, `tilts_deg`).")
        _check_angles("azimuths_deg", self.azimuths_deg, 180.0, "azimuth in the antenna frame, positive to the left")
        _check_angles("tilts_deg", self.tilts_deg, 90.0, "tilt, positive down")
        if not 1 <= self.active_h <= MAX_ELEMENTS or not 1 <= self.active_v <= MAX_ELEMENTS:
            raise ConfigError(
                f"`active_h` × `active_v` = {self.active_h} × {self.active_v}: the SSB sub-array needs "
                f"1…{MAX_ELEMENTS} elements per axis."
            )

    @property
    def num_beams(self) -> int:
        return len(self.azimuths_deg) * len(self.tilts_deg)

    def weights(self, array: ArrayGeometry, wavelength_m: float) -> torch.Tensor:
        if self.active_h > array.num_h or self.active_v > array.num_v:
            raise ConfigError(
                f"SSB sub-array {self.active_h} × {self.active_v} does not fit the {array.num_h} × {array.num_v} array."
            )
        tilt, az = np.meshgrid(np.deg2rad(self.tilts_deg), np.deg2rad(self.azimuths_deg), indexing="ij")
        el = -tilt.ravel()
        d0 = np.stack((np.cos(el) * np.cos(az.ravel()), np.cos(el) * np.sin(az.ravel()), np.sin(el)), axis=-1)
        pos = array.element_positions()  # [h, v, 3]
        phase = -(2 * np.pi / wavelength_m) * np.einsum("hvk,bk->bhv", pos, d0)
        h0 = (array.num_h - self.active_h) // 2
        v0 = (array.num_v - self.active_v) // 2
        mask = np.zeros((array.num_h, array.num_v))
        mask[h0 : h0 + self.active_h, v0 : v0 + self.active_v] = 1.0
        w = mask * np.exp(1j * phase) / np.sqrt(self.active_h * self.active_v)
        return torch.as_tensor(w, dtype=torch.complex128)


@dataclass(frozen=True)
class DFTCodebook:
    """3GPP TS 38.214 Type I single-panel DFT beams (one port per element).

    Beam (l, m) has weights exp(−j2π l h/(O1 N1)) · exp(+j2π m v/(O2 N2)) / √(N1 N2):
    ``l`` steers to the boresight's left for l > 0, ``m`` steers down for m > 0.
    ``beams_h`` × ``beams_v`` select the beams (vertical-major order).  The
    default 8 × 4 = 32 beams spread ±61° in azimuth and 0…32° down at 0.5 λ /
    0.7 λ spacing.
    """

    type: Literal["dft"] = "dft"
    n1: int = 8
    n2: int = 4
    o1: int = 2
    o2: int = 2
    beams_h: tuple[int, ...] = (-7, -5, -3, -1, 1, 3, 5, 7)
    beams_v: tuple[int, ...] = (0, 1, 2, 3)

    def __post_init__(self) -> None:
        if min(self.n1, self.n2, self.o1, self.o2) < 1 or max(self.n1, self.n2) > MAX_ELEMENTS:
            raise ConfigError(
                f"a DFT codebook needs N1, N2 in 1…{MAX_ELEMENTS} and O1, O2 >= 1 "
                f"(got n1={self.n1}, n2={self.n2}, o1={self.o1}, o2={self.o2})."
            )
        if max(self.o1, self.o2) > MAX_OVERSAMPLING:
            raise ConfigError(
                f"`o1`, `o2` = {self.o1}, {self.o2}: oversampling factors are 1…{MAX_OVERSAMPLING} "
                "(TS 38.214 uses 1 or 4)."
            )
        if not self.beams_h or not self.beams_v:
            raise ConfigError("a DFT codebook needs at least one horizontal and one vertical beam index.")
        axes = (("beams_h", self.beams_h, self.o1 * self.n1), ("beams_v", self.beams_v, self.o2 * self.n2))
        for key, beams, size in axes:
            bad = [b for b in beams if abs(b) >= size]
            if bad:
                raise ConfigError(
                    f"`{key}` = {bad[0]} is beyond the {size} DFT beams (O × N = {size}); indices lie in "
                    f"−{size - 1}…{size - 1}."
                )
            aliased = [b for i, b in enumerate(beams) if any((b - c) % size == 0 for c in beams[:i])]
            if aliased:
                raise ConfigError(
                    f"`{key}` lists the beam {aliased[0]} twice (indices equal modulo O × N = {size} are the same "
                    "beam); drop the duplicate."
                )

    @property
    def num_beams(self) -> int:
        return len(self.beams_h) * len(self.beams_v)

    def weights(self, array: ArrayGeometry, wavelength_m: float) -> torch.Tensor:
        if (array.num_h, array.num_v) != (self.n1, self.n2):
            raise ConfigError(
                f"DFT codebook N1 × N2 = {self.n1} × {self.n2} does not match the {array.num_h} × {array.num_v} array."
            )
        h = np.arange(self.n1)
        v = np.arange(self.n2)
        m, l_ = np.meshgrid(np.asarray(self.beams_v), np.asarray(self.beams_h), indexing="ij")
        ph = np.exp(-2j * np.pi * np.outer(l_.ravel(), h) / (self.o1 * self.n1))  # [beams, h]
        pv = np.exp(2j * np.pi * np.outer(m.ravel(), v) / (self.o2 * self.n2))  # [beams, v]
        w = ph[:, :, None] * pv[:, None, :] / np.sqrt(self.n1 * self.n2)
        return torch.as_tensor(w, dtype=torch.complex128)


@dataclass(frozen=True)
class WeightsCodebook:
    """Explicit per-beam element weights from a file (a vendor's beam set), see docs/codebooks.md.

    ``file`` (relative to the scenario folder) is ``.npy`` complex ``[num_beams, num_h, num_v]`` or a
    CSV/Parquet table ``beam_id, element_h, element_v, re, im``.  Each beam is normalised to unit power
    (Σ_e |W_e|² = 1): the file gives the beam *shape*, the cell's ``tx_power_dbm`` its power.  The
    electrical tilt taper is applied on top, as for the built-in kinds.
    """

    type: Literal["weights"] = "weights"
    file: str = ""

    def __post_init__(self) -> None:
        if not self.file:
            raise ConfigError("a `type: weights` codebook needs `file:` (a .npy, CSV or Parquet weights file).")

    def load(self, root: Path) -> None:
        """Read, validate and cache the weights (normalised to unit power per beam)."""
        w = read_weights_file(resolve_inside(root, self.file, "file"))
        object.__setattr__(self, "_values", w)

    @property
    def values(self) -> np.ndarray:
        """``[num_beams, num_h, num_v]`` complex, unit power per beam."""
        w: np.ndarray | None = getattr(self, "_values", None)
        if w is None:
            raise ConfigError(f"weights codebook file {self.file!r} was never loaded (load the scenario first).")
        return w

    @property
    def num_beams(self) -> int:
        return int(self.values.shape[0])

    def weights(self, array: ArrayGeometry, wavelength_m: float) -> torch.Tensor:
        w = self.values
        if w.shape[1:] != (array.num_h, array.num_v):
            raise ConfigError(
                f"weights file {self.file!r} has {w.shape[1]} × {w.shape[2]} elements per beam, which does not "
                f"match the {array.num_h} × {array.num_v} array."
            )
        return torch.as_tensor(w, dtype=torch.complex128)


@dataclass(frozen=True)
class PatternCodebook:
    """Measured per-beam 3-D gain patterns from a table (a massive-MIMO vendor's beam set), see docs/codebooks.md.

    ``file`` (relative to the scenario folder) is a CSV/Parquet table ``beam_id, azimuth_deg, elevation_deg,
    gain_dbi`` on a full azimuth × elevation grid in the *antenna* frame (azimuth positive to the
    boresight's left, elevation positive up).  The gain already includes element and array gain, so a
    beam's sensing row is ``P_t · G_beam(ω')`` with no element pattern, array or electrical tilt applied
    (the tilt is in the measurement; mechanical tilt and azimuth still rotate the antenna frame).
    """

    type: Literal["pattern"] = "pattern"
    file: str = ""
    frequency_hz: float | None = None
    """Carrier the patterns were measured at [Hz]; a cell on another band (±10 %) is refused."""

    def __post_init__(self) -> None:
        if not self.file:
            raise ConfigError("a `type: pattern` codebook needs `file:` (a CSV or Parquet gain table).")
        if self.frequency_hz is not None and not (np.isfinite(self.frequency_hz) and self.frequency_hz > 0):
            raise ConfigError(f"`frequency_hz` = {self.frequency_hz!r} must be a positive frequency [Hz].")

    def load(self, root: Path) -> None:
        """Read, validate and cache the gain grids."""
        az, el, gain_db = read_pattern_table(resolve_inside(root, self.file, "file"))
        object.__setattr__(self, "_grid", (az, el, gain_db))

    @property
    def grid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Sorted azimuths [deg] ``[n_az]``, elevations [deg] ``[n_el]``, gains [dBi] ``[beams, n_el, n_az]``."""
        g: tuple[np.ndarray, np.ndarray, np.ndarray] | None = getattr(self, "_grid", None)
        if g is None:
            raise ConfigError(f"pattern codebook file {self.file!r} was never loaded (load the scenario first).")
        return g

    @property
    def num_beams(self) -> int:
        return int(self.grid[2].shape[0])

    def weights(self, array: ArrayGeometry, wavelength_m: float) -> torch.Tensor:
        raise ConfigError(
            f"pattern codebook {self.file!r} has measured gains, not element weights; it cannot be re-steered "
            "(choose among named codebooks instead)."
        )

    def gain_lin(self, local: torch.Tensor) -> torch.Tensor:
        """Linear gain ``[num_beams, num_dirs]`` towards antenna-frame unit vectors ``local [num_dirs, 3]``.

        Bilinear in (azimuth, elevation) with azimuth wrap-around; elevations beyond the table's range take
        the nearest row (the table should cover −90…90°).
        """
        az_grid, el_grid, gain_db = self.grid
        x = local.detach().to(torch.float64).cpu().numpy()
        az = np.rad2deg(np.arctan2(x[:, 1], x[:, 0]))
        el = np.rad2deg(np.arcsin(np.clip(x[:, 2], -1.0, 1.0)))
        # azimuth: periodic axis; append the first column shifted by 360°
        az_ext = np.concatenate((az_grid, [az_grid[0] + 360.0]))
        lin = 10.0 ** (gain_db / 10.0)
        lin_ext = np.concatenate((lin, lin[:, :, :1]), axis=2)
        a = (az - az_grid[0]) % 360.0 + az_grid[0]
        ia = np.clip(np.searchsorted(az_ext, a, side="right") - 1, 0, len(az_ext) - 2)
        ta = (a - az_ext[ia]) / (az_ext[ia + 1] - az_ext[ia])
        e = np.clip(el, el_grid[0], el_grid[-1])
        if len(el_grid) == 1:
            ie = np.zeros_like(ia)
            te = np.zeros_like(ta)
            lin_ext = np.concatenate((lin_ext, lin_ext), axis=1)
        else:
            ie = np.clip(np.searchsorted(el_grid, e, side="right") - 1, 0, len(el_grid) - 2)
            te = (e - el_grid[ie]) / (el_grid[ie + 1] - el_grid[ie])
        g = (
            lin_ext[:, ie, ia] * (1 - te) * (1 - ta)
            + lin_ext[:, ie, ia + 1] * (1 - te) * ta
            + lin_ext[:, ie + 1, ia] * te * (1 - ta)
            + lin_ext[:, ie + 1, ia + 1] * te * ta
        )
        return torch.as_tensor(g, dtype=local.dtype, device=local.device)


MAX_ELEMENTS = 1024
"""Largest number of array elements per axis (as the cells tables' ``array_nh``/``array_nv``)."""
MAX_OVERSAMPLING = 16


def _check_angles(key: str, angles: tuple[float, ...], limit: float, meaning: str) -> None:
    """Finite angles within ±``limit``°, none listed twice."""
    for value in angles:
        if not np.isfinite(value) or abs(value) > limit:
            raise ConfigError(f"`{key}` = {value!r} is outside −{limit:g}…{limit:g}° ({meaning}).")
    seen = [a for i, a in enumerate(angles) if a in angles[:i]]
    if seen:
        raise ConfigError(f"`{key}` lists {seen[0]!r} twice, which makes duplicate beams; drop the duplicate.")


Codebook = SSBCodebook | DFTCodebook | WeightsCodebook | PatternCodebook
_CODEBOOKS: dict[str, type] = {
    "ssb": SSBCodebook,
    "dft": DFTCodebook,
    "weights": WeightsCodebook,
    "pattern": PatternCodebook,
}


def codebook_from_dict(spec: dict[str, Any], where: str = "codebook", root: Path | None = None) -> Codebook:
    """Build a codebook from a YAML mapping with a ``type`` key (``ssb``, ``dft``, ``weights``, ``pattern``).

    ``root`` (the scenario folder) loads a file codebook's ``file`` at once; without it the file is read
    on first use relative to the working directory's ``root`` given later via :meth:`WeightsCodebook.load`.
    """
    if not isinstance(spec, dict) or "type" not in spec:
        raise ConfigError(f"`{where}` must be a mapping with `type:` one of {', '.join(_CODEBOOKS)}.")
    kind = spec["type"]
    if kind not in _CODEBOOKS:
        raise ConfigError(f"`{where}.type` must be one of {', '.join(sorted(_CODEBOOKS))} (got {kind!r}).")
    try:
        book: Codebook = from_dict(_CODEBOOKS[kind], spec, prefix=where)
        if root is not None and isinstance(book, (WeightsCodebook, PatternCodebook)):
            book.load(root)
    except (ConfigError, DataError) as exc:
        text = str(exc)
        raise ConfigError(text if f"`{where}" in text else f"`{where}`: {text}") from None
    return book


def electrical_tilt_taper(array: ArrayGeometry, wavelength_m: float, elec_tilt_deg: float) -> torch.Tensor:
    """Vertical phase taper ``[num_h, num_v]`` steering the pattern down by ``elec_tilt_deg``."""
    z = array.element_positions()[..., 2]
    phase = (2 * np.pi / wavelength_m) * z * np.sin(np.deg2rad(elec_tilt_deg))
    return torch.as_tensor(np.exp(1j * phase), dtype=torch.complex128)
