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


def positional_encoding_t(x: torch.Tensor, num_freqs: int, out: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`positional_encoding` of ``x [N, in_dim]``, transposed: ``[encoded_dim, N]`` (its ``.T`` is
    ``positional_encoding(x, num_freqs)`` to within ~2e-5), written into ``out`` when given (rows of a
    wider buffer, say).  ``x [k, N, in_dim]`` encodes k inputs one after another (``[k · encoded_dim, N]``,
    the same values as k calls, in 1/k of the kernel launches).

    For the decoder's per-(query, sample) geometry, the widest input of a render: every part lands in whole
    rows, so several encodings share one buffer with no concatenation, and a matrix product reads its ``.T``
    without a copy.  Only the lowest frequency is evaluated with sin/cos; each doubling follows from the
    one before (sin 2a = 2 sin a cos a, cos 2a = 1 − 2 sin² a), about 3× cheaper than sin and cos of every
    angle and as accurate in float32 as sin(2^{L−1} π x) itself.  Not differentiable (the ``out=`` kernels
    record no graph): for inputs that carry no gradient."""
    batch = x[None] if x.dim() == 2 else x
    k, n, width = batch.shape
    rows = encoded_dim(width, num_freqs)
    if out is None:
        out = x.new_empty(k * rows, n)
    elif out.shape != (k * rows, n):
        raise ValueError(f"out is {tuple(out.shape)}, the encoding {(k * rows, n)}")
    parts = out.view(k, rows, n)  # input j's encoding in rows j·rows … (j + 1)·rows − 1
    parts[:, :width] = batch.transpose(1, 2)
    if num_freqs > 0:
        span = width * num_freqs
        sin = parts[:, width : width + span].view(k, width, num_freqs, n)  # row d·L + l, as positional_encoding's
        cos = parts[:, width + span : width + 2 * span].view(k, width, num_freqs, n)
        base = parts[:, :width] * math.pi
        torch.sin(base, out=sin[:, :, 0])
        torch.cos(base, out=cos[:, :, 0])
        for level in range(1, num_freqs):
            s, c = sin[:, :, level - 1], cos[:, :, level - 1]
            torch.mul(s, c, out=sin[:, :, level]).mul_(2.0)
            torch.mul(s, s, out=cos[:, :, level]).mul_(-2.0).add_(1.0)
    return out
