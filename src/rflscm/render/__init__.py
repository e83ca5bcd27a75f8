"""The renderer: ray sampling and the APS integral.  No parameters (SPEC §3, STYLE)."""

from rflscm.render.aps import accumulate_power, chunk_bounds, chunked, render_power, segment_cumsum, transmittance
from rflscm.render.rays import (
    PackedSamples,
    RaySamples,
    build_ray_samples,
    gather_samples,
    join_queries,
    num_samples_for,
    ray_points,
    select_samples,
)

__all__ = [
    "PackedSamples",
    "RaySamples",
    "accumulate_power",
    "build_ray_samples",
    "chunk_bounds",
    "chunked",
    "gather_samples",
    "join_queries",
    "num_samples_for",
    "ray_points",
    "render_power",
    "segment_cumsum",
    "select_samples",
    "transmittance",
]
