"""Cached APS and batched candidate sensing matrices: what makes a candidate configuration cheap.

The APS lives in the world frame (SPEC §2), so a candidate antenna setting changes only A.  Per cell
we keep its APS at every grid, ``aps[num_grids, num_kept]``, on the bins where any grid has power
(dropping all-zero columns is exact: they add nothing to r = A x; :class:`rflscm.eval.cache.ScenarioAPS`,
the one APS cache of evaluation, prediction and optimisation), and build the candidate sensing
matrices of many settings at once with the very functions :func:`rflscm.antenna.sensing_matrix`
uses: one rotation → element gain and steering vectors ``[num_kept, num_elements]`` once, then one
complex product with the stacked beam weights of every (electrical tilt, codebook) candidate.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import torch

from rflscm.antenna.array import steering_vectors
from rflscm.antenna.codebook import PatternCodebook
from rflscm.antenna.sensing import beam_weights, sensing_matrix
from rflscm.eval.cache import ScenarioAPS
from rflscm.models.base import MIN_POWER_MW
from rflscm.network.space import CellOptions

if TYPE_CHECKING:
    from rflscm.data.scenario import Scenario


ApsCache = ScenarioAPS
"""The optimiser's name for :class:`rflscm.eval.cache.ScenarioAPS` (rendered, saved and checked there)."""


class CellSensing:
    """Candidate sensing matrices of one cell on its kept bins, many settings per call.

    Args:
        scenario: the scenario (array, element, power, carrier, codebooks of the cell).
        cell_id: the cell; base_round: the round whose antenna the candidates modify.
        directions: world-frame unit vectors of the kept bins ``[num_kept, 3]`` (float32).
        options: the cell's search options.
    """

    def __init__(
        self, scenario: Scenario, cell_id: int, base_round: int, directions: torch.Tensor, options: CellOptions
    ) -> None:
        self.antenna = scenario.antenna(cell_id, base_round)
        self.wavelength_m = scenario.wavelength_m(cell_id)
        self.codebooks = [scenario.meta.codebooks[name] for name in options.values["ssb_codebook"]]
        self.max_beams = max(cb.num_beams for cb in self.codebooks)
        self.directions = directions
        self.options = options
        self._weights: dict[tuple[int, int], torch.Tensor] = {}

    def _beam_weights(self, i_book: int, i_elec: int) -> torch.Tensor:
        """Unit-power weights ``[num_beams, num_elements]`` (complex64, electrical tilt included)."""
        key = (i_book, i_elec)
        if key not in self._weights:
            antenna = dataclasses.replace(self.antenna, elec_tilt_deg=self.options.values["elec_tilt_deg"][i_elec])
            w = beam_weights(
                self.codebooks[i_book],
                antenna,
                self.wavelength_m,
                dtype=torch.complex64,
            )
            self._weights[key] = w.reshape(w.shape[0], -1)
        return self._weights[key]

    def matrices(self, indices: list[tuple[int, ...]]) -> torch.Tensor:
        """Sensing matrices ``[num_candidates, max_beams, num_kept]`` [mW per unit path gain] of the
        candidates ``(i_book, i_elec, i_mech, i_az)``; a smaller codebook's extra rows are zero."""
        out = torch.zeros(len(indices), self.max_beams, self.directions.shape[0])
        groups: dict[tuple[int, int], list[int]] = {}
        for k, (_, _, i_mech, i_az) in enumerate(indices):
            groups.setdefault((i_mech, i_az), []).append(k)
        values = self.options.values
        for (i_mech, i_az), members in groups.items():
            antenna = dataclasses.replace(
                self.antenna,
                mech_tilt_deg=values["mech_tilt_deg"][i_mech],
                azimuth_deg=values["azimuth_deg"][i_az],
            )
            rot = torch.as_tensor(antenna.rotation(), dtype=torch.float32)
            local = self.directions @ rot  # world → antenna frame    [num_kept, 3]
            patterns = [k for k in members if isinstance(self.codebooks[indices[k][0]], PatternCodebook)]
            for k in patterns:  # measured beams: gain from the table; electrical tilt is in the measurement
                book = self.codebooks[indices[k][0]]
                out[k, : book.num_beams] = sensing_matrix(antenna, book, self.directions, self.wavelength_m)
            members = [k for k in members if k not in patterns]
            if not members:
                continue
            gain = antenna.element.gain_lin(local) * antenna.tx_power_mw  # [num_kept]
            steer = steering_vectors(antenna.array, local, self.wavelength_m)  # [num_kept, num_elements]
            weights = [self._beam_weights(indices[k][0], indices[k][1]) for k in members]
            response = steer @ torch.cat(weights).T  # [num_kept, sum of beams]
            power = (response.real.square() + response.imag.square()) * gain[:, None]
            start = 0
            for k, w in zip(members, weights):
                out[k, : w.shape[0]] = power[:, start : start + w.shape[0]].T
                start += w.shape[0]
        return out


def best_beam_power(
    aps: torch.Tensor, matrices: torch.Tensor, mix: tuple[torch.Tensor, torch.Tensor] | None = None
) -> torch.Tensor:
    """Best-beam RSRP ``[num_candidates, num_grids]`` [mW]: max over beams of A x for APS
    ``[num_grids, num_kept]`` and candidate matrices ``[num_candidates, num_beams, num_kept]``.  With ``mix``
    (a second APS ``[num_grids, num_kept]`` and its weight w ``[num_grids]``, :class:`~rflscm.models.source.RsrpMix`),
    each beam's power is (A x)^(1 − w) (A x₂)^w, its dB average, before the max, as ``rflscm predict`` has it."""
    c, b, n = matrices.shape
    flat = matrices.reshape(c * b, n).T
    power = aps @ flat  # [num_grids, num_candidates * num_beams]
    if mix is not None:
        other, weight = mix
        on = torch.nonzero(weight > 0).squeeze(1)
        if on.numel():
            w = weight[on].to(power.dtype)[:, None]
            own = power[on].clamp_min(MIN_POWER_MW).log()
            power[on] = torch.exp((1.0 - w) * own + w * (other[on].to(flat.dtype) @ flat).clamp_min(MIN_POWER_MW).log())
    return power.reshape(-1, c, b).amax(dim=-1).T.contiguous()
