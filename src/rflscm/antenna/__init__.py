"""Element patterns, arrays, codebooks and the beam sensing matrix."""

from rflscm.antenna.array import SPEED_OF_LIGHT, ArrayGeometry, CellAntenna, steering_vectors, wavelength_of
from rflscm.antenna.codebook import (
    Codebook,
    DFTCodebook,
    PatternCodebook,
    SSBCodebook,
    WeightsCodebook,
    codebook_from_dict,
    electrical_tilt_taper,
)
from rflscm.antenna.element import ElementPattern, MeasuredElement, TR38901Element
from rflscm.antenna.msi import read_msi, sample_msi_path, write_msi
from rflscm.antenna.sensing import beam_weights, sensing_matrix

__all__ = [
    "SPEED_OF_LIGHT",
    "ArrayGeometry",
    "CellAntenna",
    "Codebook",
    "DFTCodebook",
    "ElementPattern",
    "MeasuredElement",
    "PatternCodebook",
    "SSBCodebook",
    "TR38901Element",
    "WeightsCodebook",
    "beam_weights",
    "codebook_from_dict",
    "electrical_tilt_taper",
    "read_msi",
    "sample_msi_path",
    "sensing_matrix",
    "steering_vectors",
    "wavelength_of",
    "write_msi",
]
