"""Several independent ReLU MLPs of one shape, evaluated side by side.

Multi-seed DIAYN keeps one network per seed (and two per seed for the twin Q). :class:`StackedMLP` holds them as one
parameter tensor per network and layer and evaluates input ``[N, M, in]`` (row ``n`` for network ``n``): on a CPU
network by network, on a GPU in one ``torch.baddbmm`` per layer over the stacked parameters. Network ``n`` only ever
reads row ``n`` of the input and its own parameters, so the networks stay independent: a gradient of network ``n``'s
output reaches network ``n``'s parameters only. On a CPU they are also independent in their rounding: each network
runs the same kernels on tensors of the same shapes however many are stacked, and an optimiser steps each tensor on
its own (a fused Adam over one stacked tensor rounds the elements of its vectorised loop's tail differently from the
others, so a network's numbers would depend on its position in the stack).

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
    ``detach=True`` the parameters are read detached (the SAC actor loss reads the Q-networks so). On a CPU it runs
    network by network (:meth:`per_network_matmuls`), on a GPU in one batched matmul per layer.

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
        self.num_networks, self.depth = weights[0].shape[0], len(weights)
        # parameter layer * N + n is network n's in layer `layer`
        self.weights = nn.ParameterList([nn.Parameter(w.detach().clone()) for layer in weights for w in layer])
        self.biases = nn.ParameterList([nn.Parameter(b.detach().clone()) for layer in biases for b in layer])

    @classmethod
    def from_linears(cls, networks: Sequence[Sequence[nn.Linear]]) -> StackedMLP:
        """Stack the parameters of ``networks`` (each a list of ``nn.Linear`` of the same sizes), copied."""
        sizes = {tuple(tuple(layer.weight.shape) for layer in net) for net in networks}
        if len(sizes) != 1:
            raise ValueError(f"networks to stack must have the same layer sizes, got {sorted(sizes)}.")
        depth = len(networks[0])
        return cls([torch.stack([net[i].weight.detach() for net in networks]) for i in range(depth)],
                   [torch.stack([net[i].bias.detach() for net in networks]) for i in range(depth)])

    def layer(self, index: int) -> tuple[list[nn.Parameter], list[nn.Parameter]]:
        """Layer ``index``'s weights ``[out, in]`` and biases ``[out]``, one per network."""
        rows = slice(index * self.num_networks, (index + 1) * self.num_networks)
        return list(self.weights[rows]), list(self.biases[rows])

    def stacked(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Layer ``index``'s parameters stacked (detached copies): weights ``[N, out, in]``, biases ``[N, out]``."""
        weights, biases = self.layer(index)
        return torch.stack(weights).detach(), torch.stack(biases).detach()

    def forward(self, x: torch.Tensor, *, detach: bool = False) -> torch.Tensor:
        per_network = self.per_network_matmuls(x)
        for index in range(self.depth):
            weights, biases = self.layer(index)
            if detach:
                weights, biases = [w.detach() for w in weights], [b.detach() for b in biases]
            if per_network and self.num_networks == 1:  # views only: no copy forward or backward
                x = torch.nn.functional.linear(x.squeeze(0), weights[0], biases[0]).unsqueeze(0)
            elif per_network:
                x = torch.stack([torch.nn.functional.linear(*args) for args in zip(x.unbind(0), weights, biases)])
            else:
                x = torch.baddbmm(torch.stack(biases).unsqueeze(-2), x, torch.stack(weights).transpose(-1, -2))
            if index < self.depth - 1:
                x = torch.relu(x)
        return x

    @staticmethod
    def per_network_matmuls(x: torch.Tensor) -> bool:
        """Whether to evaluate network by network (one ``linear`` each, on a CPU) rather than in one ``baddbmm`` (on
        a GPU). On a CPU each network then runs the same kernel on the same shapes however many networks are
        stacked, so its numbers never depend on the others (MKL's batched and single GEMMs can round a weight
        gradient differently, measured: 9.5e-7), and ``bmm`` would give each thread whole matrices: one network keeps
        one of two threads busy (83 against 146 GFLOP/s for one [128, 300] @ [300, 300], measured on 2 cores)."""
        return x.device.type == "cpu"
    @torch.no_grad()
    def copy_to(self, index: int, layers: Sequence[nn.Linear]) -> None:
        """Write network ``index`` into ``layers`` (``nn.Linear`` of the same sizes), in place."""
        if len(layers) != self.depth:
            raise ValueError(f"expected {self.depth} layers, got {len(layers)}.")
        for depth, layer in enumerate(layers):
            weights, biases = self.layer(depth)
            layer.weight.copy_(weights[index])
            layer.bias.copy_(biases[index])
