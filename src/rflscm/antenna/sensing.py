"""The beam sensing matrix A (SPEC §2; paper eq. (3)).

A[m, n] = P_t · G_elem(ω'_n) · |Σ_e a_e(ω'_n) W⁽ᵐ⁾_e|²  [mW per unit path gain],

ω'_n being direction n in the antenna's own frame, a the steering vector and
W⁽ᵐ⁾ the unit-power weights of beam m (electrical tilt included).  RSRP is
then r = A x with x the APS in linear path-power gain, so A ≥ 0 always.  The
same function serves a whole :class:`AngleGrid` or any list of directions
(e.g. ray-tracer paths).
"""

from __future__ import annotations

import torch

from rflscm.antenna.array import CellAntenna, steering_vectors
from rflscm.antenna.codebook import Codebook, PatternCodebook, electrical_tilt_taper
from rflscm.geometry.grid import AngleGrid

_COMPLEX = {torch.float32: torch.complex64, torch.float64: torch.complex128}


def beam_weights(
    codebook: Codebook, antenna: CellAntenna, wavelength_m: float, dtype: torch.dtype = torch.complex128
) -> torch.Tensor:
    """Unit-power beam weights ``[num_beams, num_h, num_v]`` including the electrical tilt taper."""
    w = codebook.weights(antenna.array, wavelength_m)
    taper = electrical_tilt_taper(antenna.array, wavelength_m, antenna.elec_tilt_deg)
    return (w * taper).to(dtype)


def sensing_matrix(
    antenna: CellAntenna,
    codebook: Codebook,
    directions: AngleGrid | torch.Tensor,
    wavelength_m: float,
    dtype: torch.dtype = torch.float32,
    device: torch.device | str | None = None,
    element_gains: torch.Tensor | None = None,
) -> torch.Tensor:
    """Sensing matrix ``A [num_beams, num_dirs]`` in mW per unit path gain.

    Args:
        antenna: orientation, array, element pattern and RS power of the cell.
        codebook: the beams (rows of A).
        directions: an :class:`AngleGrid` (columns = its bins in flat order) or
            world-frame unit vectors ``[num_dirs, 3]`` (ENU).
        wavelength_m: carrier wavelength [m].
        dtype: ``torch.float32`` or ``torch.float64``.
        device: where to compute; defaults to the directions' device (CPU for a grid).
        element_gains: complex per-element gains ``[num_h, num_v]`` of a *real* array (amplitude and
            phase errors, see :mod:`rflscm.sim.field`) multiplying the beam weights; ``None`` = the
            nominal array (all ones).  Only the simulator's truth uses them; models never do.
    """
    if dtype not in _COMPLEX:
        raise TypeError(f"sensing_matrix dtype must be float32 or float64, got {dtype}")
    if isinstance(directions, AngleGrid):
        dirs = directions.directions(dtype=dtype, device=device)
    else:
        dirs = directions.to(dtype=dtype, device=device if device is not None else directions.device)
    rot = torch.as_tensor(antenna.rotation(), dtype=dtype, device=dirs.device)
    local = dirs @ rot  # world → antenna frame: (Rᵀ d)ᵀ = dᵀ R    [num_dirs, 3]
    if isinstance(codebook, PatternCodebook):
        # measured beams: element, array, tilt (and a real array's errors: element_gains) are in the pattern
        return (antenna.tx_power_mw * codebook.gain_lin(local)).contiguous()
    gain_elem = antenna.element.gain_lin(local)  # [num_dirs]
    steer = steering_vectors(antenna.array, local, wavelength_m)  # [num_dirs, num_elem]
    w = beam_weights(codebook, antenna, wavelength_m, dtype=_COMPLEX[dtype]).to(dirs.device)
    if element_gains is not None:
        w = w * element_gains.to(dtype=w.dtype, device=w.device)[None]  # [num_beams, num_h, num_v]
    response = steer @ w.reshape(w.shape[0], -1).T  # [num_dirs, num_beams]
    beam_gain = response.real.square() + response.imag.square()
    return (antenna.tx_power_mw * gain_elem[:, None] * beam_gain).T.contiguous()
