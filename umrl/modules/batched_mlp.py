"""Task-batched evaluation of the Gaussian MLP policy: every task's weights in one ``baddbmm`` per layer.

MAML keeps one parameter set per task (batch ``[T]``: weights ``[T, out, in]``, biases ``[T, out]``). Evaluating
them with a Python loop of ``functional_call`` or with ``torch.func.vmap`` costs per-call Python/TensorDict work on
every forward and every (double) backward; here the whole ``[T, M, in]`` input goes through each layer as one batched
matmul, whose backward and double backward are batched matmuls too.

:func:`umrl.modules.policy.make_gaussian_policy` declares its network's layers when it builds it
(:func:`declare_batched_layers`: the MLP of ``nn.Linear`` and element-wise activations and the
``AddStateIndependentNormalScale`` head, recorded on the loc/scale ``TensorDictModule``); a layer this evaluation
cannot run makes the declaration, and so the policy's construction, fail. :meth:`BatchedGaussianMLP.from_net` reads
the declaration and finds each parameter's key by identity, so nesting and naming are free to change. A network
without a declaration, or one changed since (a layer replaced), gets ``None``, and callers evaluate it with ``vmap``.

:class:`ReLUMLPLinearization` differentiates such a network by hand when it is a ReLU MLP: forward tangents,
gradients and their directional derivatives as batched matmuls over the kept activations, without an autograd graph
(``umrl.optim.meta_hvp.AnalyticHVP`` builds the KL Hessian-vector product on them).
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from tensordict.nn.utils import mappings
from torch import nn

__all__ = ["BatchedGaussianMLP", "ReLUMLPLinearization", "declare_batched_layers"]

_ELEMENTWISE = (nn.ReLU, nn.Tanh, nn.ELU, nn.LeakyReLU, nn.SiLU, nn.GELU, nn.Sigmoid, nn.Softplus, nn.Identity)
DECLARATION = "batched_mlp_layers"
"""Attribute of the loc/scale ``TensorDictModule`` holding its declared ``(mlp, head)``."""


def declare_batched_layers(module: TensorDictModule, mlp: nn.Sequential, head: AddStateIndependentNormalScale) -> None:
    """Declare that ``module`` computes ``(loc, scale)`` as ``head(mlp(inputs))`` (inputs concatenated), so
    :class:`BatchedGaussianMLP` evaluates it for per-task parameters; ``ValueError`` if it cannot (a layer other
    than ``nn.Linear`` and element-wise activations, another head)."""
    BatchedGaussianMLP._from_parts(module, module, mlp, head)
    setattr(module, DECLARATION, (mlp, head))


class BatchedGaussianMLP:
    """``(loc, scale)`` of a Gaussian MLP policy for per-task parameters, all tasks in one batched call per layer.

    Build it with :meth:`from_net` (``None`` if the network is not a plain Gaussian MLP). Call it with the per-task
    parameter TensorDict (batch ``[T]``, keys as in ``TensorDict.from_module(net)``) and the input tensors
    ``[T, *batch, in_i]`` of the net's ``in_keys`` (concatenated on the last dim); returns ``loc`` and ``scale``,
    each ``[T, *batch, act_dim]``.
    """

    def __init__(self, in_keys: list, layers: list, scale_key: tuple, scale_mapping: str, scale_lb: float):
        self.in_keys = in_keys
        self.layers = layers  # ("linear", weight_key, bias_key | None) or ("act", module)
        self.scale_key = scale_key
        self.scale_mapping = scale_mapping  # e.g. "exp": scale = exp(state_independent_scale), clamped at scale_lb
        self.scale_map = mappings(scale_mapping)
        self.scale_lb = scale_lb

    @classmethod
    def from_net(cls, net: nn.Module) -> BatchedGaussianMLP | None:
        """The declared layers of ``net`` (a ``TensorDictSequential`` of one ``TensorDictModule``, as
        ``FunctionalPolicy.net``, or that module), or ``None`` for a network that declares none or no longer matches
        its declaration.

        The parameter keys are ``net``'s own (``TensorDict.from_module(net)``), which are the policy's.
        """
        mods = list(net.module) if hasattr(net, "module") and isinstance(net.module, nn.ModuleList) else [net]
        if len(mods) != 1 or not isinstance(mods[0], TensorDictModule):
            return None
        parts = getattr(mods[0], DECLARATION, None)
        if parts is None:
            return None
        try:
            return cls._from_parts(net, mods[0], *parts)
        except ValueError:
            return None

    @classmethod
    def _from_parts(cls, net: nn.Module, module: TensorDictModule, mlp: nn.Sequential,
                    head: AddStateIndependentNormalScale) -> BatchedGaussianMLP:
        """The layers of ``mlp`` and ``head`` (submodules of ``module``, itself in ``net``), keyed as in ``net``;
        ``ValueError`` naming what does not fit."""
        keys = {id(p): tuple(name.split(".")) for name, p in net.named_parameters()}
        if not any(m is mlp for m in module.modules()) or not any(m is head for m in module.modules()):
            raise ValueError("the declared MLP and scale head are no longer part of the policy's module.")
        if not isinstance(head, AddStateIndependentNormalScale) or id(head.state_independent_scale) not in keys:
            raise ValueError(f"the scale head must be an AddStateIndependentNormalScale, got {type(head).__name__}.")
        layers = []
        for name, layer in mlp.named_children():
            if isinstance(layer, nn.Linear):
                layers.append(("linear", keys[id(layer.weight)], None if layer.bias is None else keys[id(layer.bias)]))
            elif type(layer) in _ELEMENTWISE:
                layers.append(("act", layer))
            else:
                raise ValueError(f"layer {name} of the policy's MLP is a {type(layer).__name__}; the task-batched "
                                 f"evaluation runs nn.Linear and the element-wise {[t.__name__ for t in _ELEMENTWISE]}.")
        return cls(list(module.in_keys), layers, keys[id(head.state_independent_scale)], head.scale_mapping,
                   head.scale_lb)

    def __call__(self, params: TensorDictBase, inputs: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        h, num_tasks, batch = self.flat_input(inputs)
        h = self._apply(params, self.layers, h)  # [T, M, act_dim]
        loc = h.reshape(num_tasks, *batch, h.shape[-1])
        log_scale = params.get(self.scale_key)  # [T, act_dim]
        log_scale = log_scale.view(num_tasks, *(1,) * len(batch), log_scale.shape[-1]).expand_as(loc)
        return loc, self.scale_map(log_scale).clamp_min(self.scale_lb)

    def features(self, params: TensorDictBase, inputs: list[torch.Tensor]) -> torch.Tensor:
        """What the last linear layer reads: ``[T, *batch, hidden]``, for the same ``params`` and ``inputs`` as a
        call (``loc`` is that linear layer of these features, computed by the same operations)."""
        h, num_tasks, batch = self.flat_input(inputs)
        last = max(i for i, (kind, *_) in enumerate(self.layers) if kind == "linear")
        h = self._apply(params, self.layers[:last], h)
        return h.reshape(num_tasks, *batch, h.shape[-1])

    @property
    def is_relu_mlp(self) -> bool:
        """Linear layers with a ReLU after each but the last, and an ``exp`` scale: what
        :class:`ReLUMLPLinearization` and ``umrl.optim.meta_hvp.AnalyticHVP`` differentiate by hand."""
        kinds = [kind if kind == "linear" else type(spec[0]) for kind, *spec in self.layers]
        return self.scale_mapping == "exp" and kinds == ["linear", nn.ReLU] * (len(kinds) // 2) + ["linear"]

    def linear_keys(self) -> list[tuple[tuple, tuple | None]]:
        """``(weight_key, bias_key | None)`` of each linear layer, in order."""
        return [(w, b) for _, w, b in (layer for layer in self.layers if layer[0] == "linear")]

    def linear_params(self, params: TensorDictBase) -> list[tuple[torch.Tensor, torch.Tensor | None]]:
        """``(weight [T, out, in], bias [T, out] | None)`` of each linear layer, in order."""
        return [(params.get(w), None if b is None else params.get(b)) for w, b in self.linear_keys()]

    @staticmethod
    def flat_input(inputs: list[torch.Tensor]) -> tuple[torch.Tensor, int, torch.Size]:
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


class ReLUMLPLinearization:
    """A ReLU MLP (``BatchedGaussianMLP.is_relu_mlp``) at per-task parameters on fixed inputs, differentiated by hand.

    The forward pass is run once and its layer inputs and ReLU masks kept; then, all tasks in batched matmuls
    (Pearlmutter's R-operator, no autograd graph):

    - :meth:`jvp`: the output's directional derivative ``Rμ`` for a parameter direction;
    - :meth:`vjp`: the parameters' gradient for an output gradient ``g`` (plus each layer's ``δ``, for :meth:`rvjp`);
    - :meth:`rvjp`: the directional derivative of that gradient, given how ``g`` moves (``Rg``): the Hessian-vector
      product of any loss of the output, network curvature included.

    Shapes: ``x`` ``[T, M, in]``; parameters and directions are lists of ``(weight [T, out, in], bias [T, out] |
    None)`` per linear layer; the output ``loc`` and its gradients are ``[T, M, out_last]``. Narrow results (the
    output when ``out_last`` is below the last hidden width, a weight gradient with fewer inputs than outputs) are
    transposed views.
    """

    def __init__(self, linear_params: list[tuple[torch.Tensor, torch.Tensor | None]], x: torch.Tensor):
        self.weights = [w for w, _ in linear_params]
        self.has_bias = [b is not None for _, b in linear_params]
        self.inputs = [x]  # the input of each linear layer
        self.masks = []  # ReLU derivative after each hidden layer (1 where its input > 0, as torch's ReLU backward)
        h = x
        for i, (w, b) in enumerate(linear_params):
            z = self._affine([(h, w)], b)
            if i == len(linear_params) - 1:
                self.loc = z
            else:
                self.masks.append((z > 0).to(z.dtype))
                h = z.clamp_min_(0)
                self.inputs.append(h)

    def jvp(self, direction: list) -> tuple[torch.Tensor, list]:
        """``(Rμ, Rh)``: the output's derivative along ``direction`` and each linear layer's input's (``None`` for
        the first, which does not move)."""
        r_inputs, r = [None], None
        for i, (w, (v, c)) in enumerate(zip(self.weights, direction)):
            rz = self._affine([(self.inputs[i], v)] + ([] if r is None else [(r, w)]), c)
            if i < len(self.weights) - 1:
                r = rz.mul_(self.masks[i])
                r_inputs.append(r)
        return rz, r_inputs

    def vjp(self, grad_loc: torch.Tensor) -> tuple[list, list]:
        """``(grads, deltas)``: each linear layer's ``(weight, bias)`` gradient for the output gradient
        ``grad_loc``, and the gradient ``δ`` at each linear layer's output."""
        grads, deltas, delta = [None] * len(self.weights), [None] * len(self.weights), grad_loc
        for i in reversed(range(len(self.weights))):
            deltas[i] = delta
            grads[i] = (self._sample_sum([(delta, self.inputs[i])]), delta.sum(-2) if self.has_bias[i] else None)
            if i > 0:
                delta = torch.bmm(delta, self.weights[i]).mul_(self.masks[i - 1])
        return grads, deltas

    def rvjp(self, direction: list, r_inputs: list, deltas: list, r_grad_loc: torch.Tensor) -> list:
        """The derivative along ``direction`` of :meth:`vjp`'s ``grads``, where the output gradient moves by
        ``r_grad_loc`` (``r_inputs``: :meth:`jvp`'s; ``deltas``: :meth:`vjp`'s)."""
        grads, r = [None] * len(self.weights), r_grad_loc
        for i in reversed(range(len(self.weights))):
            moved_input = [] if r_inputs[i] is None else [(deltas[i], r_inputs[i])]
            grads[i] = (self._sample_sum([(r, self.inputs[i])] + moved_input), r.sum(-2) if self.has_bias[i] else None)
            if i > 0:
                r = torch.bmm(r, self.weights[i]).baddbmm_(deltas[i], direction[i][0]).mul_(self.masks[i - 1])
        return grads

    # MKL's batched GEMM is several times slower writing a narrow output (a few columns: the action mean, a first
    # layer's weight gradient) than writing it transposed (a few rows): 2.4 -> 0.8 ms for [40, 2000, 100] @ [100, 2],
    # 49 -> 11 ms for a [50, 300, 2] weight gradient over 4000 samples (2 threads). Such outputs are computed as the
    # transpose of the transposed product and returned as a view.

    @staticmethod
    def _affine(terms: list[tuple[torch.Tensor, torch.Tensor]], bias: torch.Tensor | None) -> torch.Tensor:
        """``Σ_k x_k w_kᵀ (+ bias)``: ``x_k`` ``[T, M, in_k]``, ``w_k`` ``[T, out, in_k]``, ``bias`` ``[T, out]`` ->
        ``[T, M, out]``."""
        narrow = terms[0][1].shape[-2] < terms[0][1].shape[-1]  # out < in: computed as (Σ w_k x_kᵀ + bias)ᵀ
        (a, b), *rest = [(w, x.mT) if narrow else (x, w.mT) for x, w in terms]
        out = torch.bmm(a, b) if bias is None else torch.baddbmm(bias.unsqueeze(-1 if narrow else -2), a, b)
        for a, b in rest:
            out.baddbmm_(a, b)
        return out.mT if narrow else out

    @staticmethod
    def _sample_sum(terms: list[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
        """``Σ_k a_kᵀ b_k`` over the samples: ``a_k`` ``[T, M, out]``, ``b_k`` ``[T, M, in]`` -> ``[T, out, in]``."""
        narrow = terms[0][1].shape[-1] < terms[0][0].shape[-1]  # in < out: computed as (Σ b_kᵀ a_k)ᵀ
        (a, b), *rest = [(b, a) if narrow else (a, b) for a, b in terms]
        out = torch.bmm(a.mT, b)
        for a, b in rest:
            out.baddbmm_(a.mT, b)
        return out.mT if narrow else out
