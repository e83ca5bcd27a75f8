"""Positional (Fourier-feature) encoding of decoder inputs (NeRF, Mildenhall et al. 2020, eq. (4))."""

from __future__ import annotations

import math

import torch


def encoded_dim(in_dim: int, num_freqs: int, include_input: bool = True) -> int:
    """Width of :func:`positional_encoding` for ``in_dim`` inputs."""
    return in_dim * (2 * num_freqs + (1 if include_input else 0))


def positional_encoding(x: torch.Tensor, num_freqs: int, include_input: bool = True) -> torch.Tensor:
    """``[..., in_dim]`` → ``[..., in_dim · (2 num_freqs + include_input)]``.

    γ(x) = (x, sin(2⁰ π x), cos(2⁰ π x), …, sin(2^{L−1} π x), cos(2^{L−1} π x)) with
    L = ``num_freqs``; inputs are expected in roughly [−1, 1].
    """
    parts = [x] if include_input else []
    if num_freqs > 0:
        freqs = math.pi * 2.0 ** torch.arange(num_freqs, dtype=x.dtype, device=x.device)  # [L]
        angles = (x[..., None] * freqs).flatten(-2)  # [..., in_dim · L]
        parts += [torch.sin(angles), torch.cos(angles)]
    return torch.cat(parts, dim=-1)
