"""Layers whose weights are stacked over experts: ``M`` independent networks in one batched call.

Inputs and outputs are expert-major, ``[M, B, features]``: expert ``i`` uses weight ``W[i]`` on
row ``i``, one ``baddbmm`` per layer (the weight enters transposed as a view, so nothing is copied).
A batch-major ``einsum("bmi,moi->bmo")`` computes the same but permutes its operands to this layout
and back on every call; in a training step those copies cost more than the matrix products.
"""

from __future__ import annotations

import math

import torch
from torch import nn


class StackedLinear(nn.Module):
    """``y[i, b] = W[i] x[i, b] + c[i]`` for ``M`` experts at once (``x [M, B, in]``)."""

    def __init__(self, n_experts: int, in_features: int, out_features: int):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(n_experts, out_features, in_features))
        self.bias = nn.Parameter(torch.empty(n_experts, out_features))
        bound = 1.0 / math.sqrt(in_features)
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.baddbmm(self.bias.unsqueeze(1), x, self.weight.transpose(1, 2))


class StackedGRUCell(nn.Module):
    """``M`` GRU cells (``nn.GRUCell`` equations, gate order r, z, n) on ``[M, B, in]`` inputs."""

    def __init__(self, n_experts: int, input_size: int, hidden_size: int):
        super().__init__()
        self.hidden_size = hidden_size
        self.weight_ih = nn.Parameter(torch.empty(n_experts, 3 * hidden_size, input_size))
        self.weight_hh = nn.Parameter(torch.empty(n_experts, 3 * hidden_size, hidden_size))
        self.bias_ih = nn.Parameter(torch.empty(n_experts, 3 * hidden_size))
        self.bias_hh = nn.Parameter(torch.empty(n_experts, 3 * hidden_size))
        bound = 1.0 / math.sqrt(hidden_size)
        for p in self.parameters():
            nn.init.uniform_(p, -bound, bound)

    def forward(self, x: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
        gi = torch.baddbmm(self.bias_ih.unsqueeze(1), x, self.weight_ih.transpose(1, 2))
        gh = torch.baddbmm(self.bias_hh.unsqueeze(1), h, self.weight_hh.transpose(1, 2))
        i_r, i_z, i_n = gi.chunk(3, dim=-1)
        h_r, h_z, h_n = gh.chunk(3, dim=-1)
        r = torch.sigmoid(i_r + h_r)
        z = torch.sigmoid(i_z + h_z)
        n = torch.tanh(i_n + r * h_n)
        return n + z * (h - n)
