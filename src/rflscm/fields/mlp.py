"""Small fully connected networks (the radiance decoder 𝒬 and MLP fields)."""

from __future__ import annotations

import torch
from torch import nn


class MLP(nn.Module):
    """``num_layers`` hidden ReLU layers of width ``hidden``, then a linear output layer.

    ``skip_at`` re-injects the input after that many hidden layers (NeRF's skip connection).
    ``out_scale`` scales the initial weights of the output layer (0 → the network starts as
    its output bias, which the owner sets), so an untrained model is smooth and predictable.
    """

    def __init__(
        self,
        in_dim: int,
        out_dim: int,
        hidden: int = 64,
        num_layers: int = 2,
        skip_at: int | None = None,
        out_scale: float = 1.0,
    ) -> None:
        super().__init__()
        self.skip_at = skip_at
        layers = []
        width = in_dim
        for i in range(num_layers):
            if skip_at is not None and i == skip_at:
                width += in_dim
            layers.append(nn.Linear(width, hidden))
            width = hidden
        self.hidden = nn.ModuleList(layers)
        self.out = nn.Linear(width, out_dim)
        with torch.no_grad():
            self.out.weight.mul_(out_scale)
            self.out.bias.zero_()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``[..., in_dim]`` → ``[..., out_dim]``."""
        h = x
        for i, layer in enumerate(self.hidden):
            if self.skip_at is not None and i == self.skip_at:
                h = torch.cat((h, x), dim=-1)
            h = layer(h).relu_()  # in place: the linear layer's backward does not need its output
        return self.out(h)
