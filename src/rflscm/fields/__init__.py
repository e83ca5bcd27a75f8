"""Fields: positions (and conditioning) → per-voxel quantities; nothing here knows about beams.

* :mod:`~rflscm.fields.tensor_vm` — TensoRF VM tensors 𝒢_δ, 𝒢_R (paper §IV-A);
* :mod:`~rflscm.fields.fdam` — FDAM δ(μ, ε, λ) and the passive medium parameterisation;
* :mod:`~rflscm.fields.point_prior` — the point-cloud prior Φ;
* :mod:`~rflscm.fields.surfaces` — the scan's surface orientation (the decoder's specular cue);
* :mod:`~rflscm.fields.mlp`, :mod:`~rflscm.fields.encoding` — the radiance decoder's parts.
"""

from rflscm.fields.encoding import encoded_dim, positional_encoding, positional_encoding_t
from rflscm.fields.fdam import PassiveMedium, fdam_attenuation
from rflscm.fields.mlp import MLP
from rflscm.fields.point_prior import PointPrior, density_grid, modulate, phi_of_density
from rflscm.fields.tensor_vm import TensorVM, resolution_for

__all__ = [
    "MLP",
    "PassiveMedium",
    "PointPrior",
    "TensorVM",
    "density_grid",
    "encoded_dim",
    "fdam_attenuation",
    "modulate",
    "phi_of_density",
    "positional_encoding",
    "positional_encoding_t",
    "resolution_for",
]
