"""Positional encoding: the transposed, buffer-writing form used for the decoder's geometry."""

from __future__ import annotations

import pytest
import torch

from rflscm.fields import encoded_dim, positional_encoding, positional_encoding_t


@pytest.mark.parametrize(("width", "freqs", "scale"), [(3, 6, 1.0), (3, 4, 3.0), (1, 1, 1.0), (2, 0, 5.0)])
def test_the_transposed_encoding_equals_the_encoding(width: int, freqs: int, scale: float) -> None:
    x = scale * (2.0 * torch.rand(5000, width, generator=torch.Generator().manual_seed(width + freqs)) - 1.0)
    t = positional_encoding_t(x, freqs)
    assert t.shape == (encoded_dim(width, freqs), 5000)
    # the doublings carry float32 rounding, growing ×2 per level: within what sin(2^(L−1) π x) itself carries
    torch.testing.assert_close(t.T, positional_encoding(x, freqs), atol=3e-5, rtol=0.0)


def test_it_writes_into_rows_of_a_wider_buffer_and_refuses_a_wrong_shape() -> None:
    x = torch.rand(100, 3, generator=torch.Generator().manual_seed(0))
    buf = torch.full((50, 100), 7.0)
    out = positional_encoding_t(x, 6, buf[5:44])
    assert out.data_ptr() == buf[5:44].data_ptr()
    torch.testing.assert_close(buf[5:44].T, positional_encoding(x, 6), atol=3e-5, rtol=0.0)
    assert bool((buf[:5] == 7.0).all()) and bool((buf[44:] == 7.0).all())  # nothing outside its rows
    with pytest.raises(ValueError, match="out is"):
        positional_encoding_t(x, 6, buf[:10])


def test_a_batch_of_inputs_encodes_as_one_call_each() -> None:
    """Issue 29: ``[k, N, d]`` inputs give k encodings one after another, equal to the bit to k calls."""
    x = 2.0 * torch.rand(3, 700, 3, generator=torch.Generator().manual_seed(5)) - 1.0
    buf = torch.full((3 * 39 + 2, 700), 7.0)
    positional_encoding_t(x, 6, buf[1:-1])
    for k in range(3):
        assert torch.equal(buf[1 + 39 * k : 1 + 39 * (k + 1)], positional_encoding_t(x[k], 6))
    assert bool((buf[0] == 7.0).all()) and bool((buf[-1] == 7.0).all())
    with pytest.raises(ValueError, match="out is"):
        positional_encoding_t(x, 6, buf[:39])
