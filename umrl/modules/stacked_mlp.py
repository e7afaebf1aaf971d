"""Several independent ReLU MLPs of one shape, evaluated side by side.

Multi-seed DIAYN keeps one network per seed (and two per seed for the twin Q). :class:`StackedMLP` holds their
parameters stacked on a leading ``[N]`` axis (weights ``[N, out, in]``, biases ``[N, out]``) and evaluates input
``[N, M, in]`` (row ``n`` for network ``n``) in one ``torch.baddbmm`` per layer, or network by network where that is
faster (:meth:`StackedMLP.per_network_matmuls`). Network ``n`` only ever reads row ``n`` of the input and of every
parameter, so the networks stay independent: a gradient of network ``n``'s output reaches network ``n``'s parameters
only. Their rounding is not always independent of the stack: a batched and a single GEMM, and a fused optimiser's
vectorised loop over a stacked tensor, may round an element differently (measured in multi-seed DIAYN: a seed trained
among three and alone differ by at most 3e-8 after 23-82 updates, float32; ``tests/test_diayn_seeds.py``).

It is built from, and written back to, ordinary ``nn.Linear`` stacks (TorchRL's :class:`~torchrl.modules.MLP`):
:meth:`StackedMLP.from_linears` copies each network's ``nn.Linear`` layers in order, :meth:`StackedMLP.copy_to`
writes network ``n`` back into such a stack, so per-seed checkpoints stay in the single-network format.

Besides autograd, :meth:`StackedMLP.forward_saving` and :meth:`StackedMLP.backward` give a hand-derived backward pass
(the activations kept in the forward, two matmuls and one ReLU mask per layer, no autograd graph), which multi-seed
DIAYN's update uses (:meth:`umrl.objectives.stacked_diayn.StackedDIAYNLoss.gradients`).
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

    PER_NETWORK_BELOW = 1.5
    """On a CPU, networks are evaluated one by one when fewer than this many per torch thread are stacked."""

    def __init__(self, weights: Sequence[torch.Tensor], biases: Sequence[torch.Tensor]):
        super().__init__()
        if len(weights) != len(biases) or not weights:
            raise ValueError(f"need one bias per weight and at least one layer, got {len(weights)} weights and "
                             f"{len(biases)} biases.")
        self.weights = nn.ParameterList([nn.Parameter(w.detach().clone()) for w in weights])
        self.biases = nn.ParameterList([nn.Parameter(b.detach().clone()) for b in biases])

    @classmethod
    def from_linears(cls, networks: Sequence[Sequence[nn.Linear]]) -> StackedMLP:
        """Stack the parameters of ``networks`` (each a list of ``nn.Linear`` of the same sizes), copied."""
        sizes = {tuple(tuple(layer.weight.shape) for layer in net) for net in networks}
        if len(sizes) != 1:
            raise ValueError(f"networks to stack must have the same layer sizes, got {sorted(sizes)}.")
        depth = len(networks[0])
        return cls([torch.stack([net[i].weight.detach() for net in networks]) for i in range(depth)],
                   [torch.stack([net[i].bias.detach() for net in networks]) for i in range(depth)])

    @property
    def num_networks(self) -> int:
        return self.weights[0].shape[0]

    @property
    def depth(self) -> int:
        return len(self.weights)

    def forward(self, x: torch.Tensor, *, detach: bool = False) -> torch.Tensor:
        per_network = self.per_network_matmuls(x)
        for index, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            if detach:
                weight, bias = weight.detach(), bias.detach()
            if per_network and len(weight) == 1:  # views only: no copy forward or backward
                x = torch.nn.functional.linear(x.squeeze(0), weight.squeeze(0), bias.squeeze(0)).unsqueeze(0)
            elif per_network:  # unbind: one backward node per layer (a select's backward would zero-fill each)
                x = torch.stack([torch.nn.functional.linear(*args)
                                 for args in zip(x.unbind(0), weight.unbind(0), bias.unbind(0))])
            else:
                x = torch.baddbmm(bias.unsqueeze(-2), x, weight.transpose(-1, -2))
            if index < self.depth - 1:
                x = torch.relu(x)
        return x

    @torch.no_grad()
    def forward_saving(self, x: torch.Tensor, *, per_network: bool | None = None) -> list[torch.Tensor]:
        """``[x, h_1, ..., h_{L-1}, y]`` for input ``x`` [N, M, in]: the input, every hidden layer's output (after
        its ReLU) and the output ``y`` [N, M, out], as :meth:`forward` computes them, for :meth:`backward`.
        ``per_network``: evaluate network by network (None: :meth:`per_network_matmuls` decides; a compiled caller
        passes the decision in, as ``torch.get_num_threads`` cannot be traced)."""
        per_network = self.per_network_matmuls(x) if per_network is None else per_network
        activations = [x]
        for index, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            x = _matmul(x, weight.transpose(-1, -2), per_network, bias)
            if index < self.depth - 1:
                x = x.relu_()
            activations.append(x)
        return activations

    @torch.no_grad()
    def backward(self, activations: Sequence[torch.Tensor], grad_output: torch.Tensor, *,
                 weight_rows: slice | None = None, input_rows: slice | None = None,
                 input_columns: slice | None = None, per_network: bool | None = None,
                 ) -> tuple[list[torch.Tensor], list[torch.Tensor], torch.Tensor | None]:
        """Backpropagate ``grad_output`` [N, M, out] (the gradient of a loss by the output of
        :meth:`forward_saving`, which returned ``activations``): ``(weight_grads, bias_grads, grad_input)``, the
        gradients of every layer's weight [N, out, in] and bias [N, out] in layer order (no ``.grad`` is set).

        ``weight_rows``: only these rows of the batch contribute to the parameters' gradients (the others are
        propagated to the input only, as through networks read detached); None: all. ``input_rows`` and
        ``input_columns``: ``grad_input`` is the gradient by those rows and columns of the input, ``[N, rows,
        columns]`` (None for ``input_rows``: no input gradient is computed, ``grad_input`` is None).
        ``per_network`` as in :meth:`forward_saving`."""
        per_network = self.per_network_matmuls(grad_output) if per_network is None else per_network
        rows = slice(None) if weight_rows is None else weight_rows
        grad, grad_input = grad_output, None
        weight_grads, bias_grads = [None] * self.depth, [None] * self.depth
        for index in reversed(range(self.depth)):
            weight, layer_input = self.weights[index], activations[index]
            if index == 0 and input_rows is not None:
                weight_in = weight if input_columns is None else weight[..., input_columns]
                grad_input = _matmul(grad[:, input_rows], weight_in, per_network)
            weight_grads[index] = _matmul(grad[:, rows].transpose(-1, -2), layer_input[:, rows], per_network)
            bias_grads[index] = grad[:, rows].sum(-2)
            if index > 0:  # through the layer, then the ReLU in front of it (its output > 0: relu's own backward)
                grad = torch.ops.aten.threshold_backward(_matmul(grad, weight, per_network), layer_input, 0.0)
        return weight_grads, bias_grads, grad_input

    def set_grads(self, weight_grads: Sequence[torch.Tensor], bias_grads: Sequence[torch.Tensor]) -> None:
        """Set every parameter's ``.grad`` (replacing it) to :meth:`backward`'s gradients."""
        for parameter, grad in zip((*self.weights, *self.biases), (*weight_grads, *bias_grads), strict=True):
            parameter.grad = grad

    def per_network_matmuls(self, x: torch.Tensor) -> bool:
        """Whether to evaluate network by network (one ``linear`` each) rather than in one ``baddbmm``: on a CPU
        when fewer than :attr:`PER_NETWORK_BELOW` networks per torch thread are stacked. CPU ``bmm`` gives each
        thread whole matrices, so one or two networks keep one thread of two busy (83 against 146 GFLOP/s for one
        [128, 300] @ [300, 300] on 2 cores, measured), while six fill both (173 GFLOP/s)."""
        return x.device.type == "cpu" and self.num_networks < self.PER_NETWORK_BELOW * torch.get_num_threads()

    @torch.no_grad()
    def copy_to(self, index: int, layers: Sequence[nn.Linear]) -> None:
        """Write network ``index`` into ``layers`` (``nn.Linear`` of the same sizes), in place."""
        for layer, weight, bias in zip(layers, self.weights, self.biases, strict=True):
            layer.weight.copy_(weight[index])
            layer.bias.copy_(bias[index])


def _matmul(a: torch.Tensor, b: torch.Tensor, per_network: bool, bias: torch.Tensor | None = None) -> torch.Tensor:
    """``a @ b (+ bias)`` for stacks ``a`` [N, M, K], ``b`` [N, K, P], ``bias`` [N, P]: one ``bmm``/``baddbmm``, or
    one ``mm``/``addmm`` per network written into a preallocated result (``per_network``: no stacking copy)."""
    if not per_network:
        return torch.bmm(a, b) if bias is None else torch.baddbmm(bias.unsqueeze(-2), a, b)
    if a.shape[0] == 1:  # one network: its own result, viewed as a stack of one
        return (torch.mm(a[0], b[0]) if bias is None else torch.addmm(bias[0], a[0], b[0])).unsqueeze(0)
    out = a.new_empty(a.shape[0], a.shape[1], b.shape[2])
    # one unbind per operand (not one select per network and operand): fewer calls from Python
    if bias is None:
        for a_n, b_n, out_n in zip(a.unbind(0), b.unbind(0), out.unbind(0)):
            torch.mm(a_n, b_n, out=out_n)
    else:
        for a_n, b_n, out_n, bias_n in zip(a.unbind(0), b.unbind(0), out.unbind(0), bias.unbind(0)):
            torch.addmm(bias_n, a_n, b_n, out=out_n)
    return out
