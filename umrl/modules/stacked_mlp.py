"""Several independent ReLU MLPs of one shape, evaluated as one batched matmul per layer.

Multi-seed DIAYN keeps one network per seed (and two per seed for the twin Q). :class:`StackedMLP` holds their
parameters stacked on a leading ``[N]`` axis (weights ``[N, out, in]``, biases ``[N, out]``) and evaluates input
``[N, M, in]`` with one ``torch.baddbmm`` per layer, whose backward is batched matmuls too. Network ``n`` only ever
reads row ``n`` of the input and of every parameter, so the networks stay independent: a gradient of network ``n``'s
output reaches network ``n``'s parameters only.

It is built from, and written back to, ordinary ``nn.Linear`` stacks (TorchRL's :class:`~torchrl.modules.MLP`):
:meth:`StackedMLP.from_linears` copies each network's ``nn.Linear`` layers in order, :meth:`StackedMLP.copy_to`
writes network ``n`` back into such a stack, so per-seed checkpoints stay in the single-network format.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

__all__ = ["StackedMLP", "linear_layers"]


def linear_layers(module: nn.Module) -> list[nn.Linear]:
    """The ``nn.Linear`` layers of ``module`` in the order they are applied (module order, as in an ``MLP``)."""
    return [layer for layer in module.modules() if isinstance(layer, nn.Linear)]


class StackedMLP(nn.Module):
    """``N`` ReLU MLPs with the same layer sizes as stacked parameters.

    Args:
        weights: per layer, ``[N, out, in]``.
        biases: per layer, ``[N, out]``.

    ``forward(x)`` maps ``[N, M, in] -> [N, M, out]`` (ReLU between layers, none after the last); with
    ``detach=True`` the parameters are read detached (the SAC actor loss reads the Q-networks so).

    Examples:
        >>> from torchrl.modules import MLP
        >>> nets = [MLP(in_features=3, out_features=2, num_cells=[8], activation_class=nn.ReLU) for _ in range(4)]
        >>> stacked = StackedMLP.from_linears([linear_layers(n) for n in nets])
        >>> x = torch.randn(4, 5, 3)
        >>> torch.allclose(stacked(x)[2], nets[2](x[2]), atol=1e-6)
        True
    """

    def __init__(self, weights: Sequence[torch.Tensor], biases: Sequence[torch.Tensor]):
        super().__init__()
        if len(weights) != len(biases) or not weights:
            raise ValueError(f"need one bias per weight and at least one layer, got {len(weights)} weights and "
                             f"{len(biases)} biases.")
        self.weights = nn.ParameterList([nn.Parameter(w) for w in weights])
        self.biases = nn.ParameterList([nn.Parameter(b) for b in biases])

    @classmethod
    def from_linears(cls, networks: Sequence[Sequence[nn.Linear]]) -> StackedMLP:
        """Stack the parameters of ``networks`` (each a list of ``nn.Linear`` of the same sizes), copied."""
        sizes = {tuple(tuple(layer.weight.shape) for layer in net) for net in networks}
        if len(sizes) != 1:
            raise ValueError(f"networks to stack must have the same layer sizes, got {sorted(sizes)}.")
        depth = len(networks[0])
        return cls([torch.stack([net[i].weight.detach() for net in networks]).clone() for i in range(depth)],
                   [torch.stack([net[i].bias.detach() for net in networks]).clone() for i in range(depth)])

    @property
    def num_networks(self) -> int:
        return self.weights[0].shape[0]

    def forward(self, x: torch.Tensor, *, detach: bool = False) -> torch.Tensor:
        last = len(self.weights) - 1
        for i, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            if detach:
                weight, bias = weight.detach(), bias.detach()
            x = torch.baddbmm(bias.unsqueeze(-2), x, weight.transpose(-1, -2))
            if i < last:
                x = torch.relu(x)
        return x

    @torch.no_grad()
    def copy_to(self, index: int, layers: Sequence[nn.Linear]) -> None:
        """Write network ``index`` into ``layers`` (``nn.Linear`` of the same sizes), in place."""
        for layer, weight, bias in zip(layers, self.weights, self.biases, strict=True):
            layer.weight.copy_(weight[index])
            layer.bias.copy_(bias[index])
