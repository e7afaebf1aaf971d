"""Task-batched evaluation of the Gaussian MLP policy: every task's weights in one ``baddbmm`` per layer.

MAML keeps one parameter set per task (batch ``[T]``: weights ``[T, out, in]``, biases ``[T, out]``). Evaluating
them with a Python loop of ``functional_call`` or with ``torch.func.vmap`` costs per-call Python/TensorDict work on
every forward and every (double) backward; here the whole ``[T, M, in]`` input goes through each layer as one batched
matmul, whose backward and double backward are batched matmuls too.

:class:`BatchedGaussianMLP` reads the structure of the loc/scale network that
:func:`umrl.modules.policy.make_gaussian_policy` builds — ``Sequential(MLP, AddStateIndependentNormalScale)``, the MLP
made of ``nn.Linear`` and element-wise activations, optionally behind the policy's input concatenation — and returns
``None`` for any other network, so callers fall back to ``vmap``.
"""
from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from tensordict.nn.utils import mappings
from torch import nn

__all__ = ["BatchedGaussianMLP"]

_ELEMENTWISE = (nn.ReLU, nn.Tanh, nn.ELU, nn.LeakyReLU, nn.SiLU, nn.GELU, nn.Sigmoid, nn.Softplus, nn.Identity)


class BatchedGaussianMLP:
    """``(loc, scale)`` of a Gaussian MLP policy for per-task parameters, all tasks in one batched call per layer.

    Build it with :meth:`from_net` (``None`` if the network is not a plain Gaussian MLP). Call it with the per-task
    parameter TensorDict (batch ``[T]``, keys as in ``TensorDict.from_module(net)``) and the input tensors
    ``[T, *batch, in_i]`` of the net's ``in_keys`` (concatenated on the last dim); returns ``loc`` and ``scale``,
    each ``[T, *batch, act_dim]``.
    """

    def __init__(self, in_keys: list, layers: list, scale_key: tuple, scale_map: Callable, scale_lb: float):
        self.in_keys = in_keys
        self.layers = layers  # ("linear", weight_key, bias_key | None) or ("act", module)
        self.scale_key = scale_key
        self.scale_map = scale_map
        self.scale_lb = scale_lb

    @classmethod
    def from_net(cls, net: nn.Module) -> BatchedGaussianMLP | None:
        """Recognise ``net`` (a ``TensorDictSequential`` of one ``TensorDictModule``, as ``FunctionalPolicy.net``).

        The parameter keys are ``net``'s own (``TensorDict.from_module(net)``), which are the policy's.
        """
        mods = list(net.module) if hasattr(net, "module") and isinstance(net.module, nn.ModuleList) else [net]
        if len(mods) != 1 or not isinstance(mods[0], TensorDictModule):
            return None
        prefix = ("module", "0", "module") if mods[0] is not net else ("module",)
        inner = mods[0].module
        if not isinstance(inner, nn.Sequential) and isinstance(getattr(inner, "net", None), nn.Sequential):
            inner, prefix = inner.net, (*prefix, "net")  # the policy's input concatenation
        if not isinstance(inner, nn.Sequential) or len(inner) != 2:
            return None
        mlp, head = inner
        if not isinstance(mlp, nn.Sequential) or not isinstance(head, AddStateIndependentNormalScale):
            return None
        if "state_independent_scale" not in dict(head.named_parameters()):
            return None
        layers = []
        for name, layer in mlp.named_children():
            if isinstance(layer, nn.Linear):
                bias = (*prefix, "0", name, "bias") if layer.bias is not None else None
                layers.append(("linear", (*prefix, "0", name, "weight"), bias))
            elif type(layer) in _ELEMENTWISE:
                layers.append(("act", layer))
            else:
                return None
        return cls(list(mods[0].in_keys), layers, (*prefix, "1", "state_independent_scale"),
                   mappings(head.scale_mapping), head.scale_lb)

    def __call__(self, params: TensorDictBase, inputs: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        h, num_tasks, batch = self._flat_input(inputs)
        h = self._apply(params, self.layers, h)  # [T, M, act_dim]
        loc = h.reshape(num_tasks, *batch, h.shape[-1])
        log_scale = params.get(self.scale_key)  # [T, act_dim]
        log_scale = log_scale.view(num_tasks, *(1,) * len(batch), log_scale.shape[-1]).expand_as(loc)
        return loc, self.scale_map(log_scale).clamp_min(self.scale_lb)

    def features(self, params: TensorDictBase, inputs: list[torch.Tensor]) -> torch.Tensor:
        """What the last linear layer reads: ``[T, *batch, hidden]``, for the same ``params`` and ``inputs`` as a
        call (``loc`` is that linear layer of these features, computed by the same operations)."""
        h, num_tasks, batch = self._flat_input(inputs)
        last = max(i for i, (kind, *_) in enumerate(self.layers) if kind == "linear")
        h = self._apply(params, self.layers[:last], h)
        return h.reshape(num_tasks, *batch, h.shape[-1])

    @staticmethod
    def _flat_input(inputs: list[torch.Tensor]) -> tuple[torch.Tensor, int, torch.Size]:
        """The inputs concatenated and flattened to ``[T, M, in]``, with ``T`` and the batch dims between."""
        x = inputs[0] if len(inputs) == 1 else torch.cat(inputs, dim=-1)
        return x.reshape(x.shape[0], -1, x.shape[-1]), x.shape[0], x.shape[1:-1]

    @staticmethod
    def _apply(params: TensorDictBase, layers: list, h: torch.Tensor) -> torch.Tensor:
        """``layers`` on ``h`` ``[T, M, in]``: each linear layer one ``baddbmm`` (``bmm`` without a bias)."""
        for kind, *spec in layers:
            if kind == "act":
                h = spec[0](h)
                continue
            weight = params.get(spec[0])  # [T, out, in]
            if spec[1] is None:
                h = torch.bmm(h, weight.transpose(-1, -2))
            else:
                h = torch.baddbmm(params.get(spec[1]).unsqueeze(-2), h, weight.transpose(-1, -2))
        return h
