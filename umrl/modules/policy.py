"""The Gaussian MLP policy shared by MAML, VIME and the scratch baseline.

``make_gaussian_policy`` builds a TorchRL :class:`~torchrl.modules.ProbabilisticActor`: a 2×300 ReLU MLP gives the
mean, a state-independent log-std (initial std ``init_std``; learned unless ``learn_std=False``) gives the scale, and
the action is drawn from an independent Normal (no tanh: the environments clip actions to their bounds, as rllab's MAML code did). The mean
network starts as maml_rl's does (``sandbox/rocky/tf/core/utils.py``, ``make_dense_layer``): Xavier-uniform weights
and zero biases in every layer. With ``seed``, the weights are drawn from ``torch.manual_seed(seed)`` in a forked RNG,
so every method's random initialisation (MAML's, VIME's, scratch's) is the same draw for the same seed, whatever
the caller drew before.

Reads ``in_keys`` (concatenated on the last dim), writes ``"loc"``, ``"scale"``, ``"action"`` and
``"action_log_prob"``, all with the input's batch shape.
"""
from __future__ import annotations

import contextlib
import math
from collections.abc import Sequence

import torch
from tensordict.nn import AddStateIndependentNormalScale, TensorDictModule
from tensordict.nn.utils import mappings
from torch import nn
from torchrl.modules import MLP, IndependentNormal, ProbabilisticActor

from umrl.modules.batched_mlp import declare_batched_layers
from umrl.validation import check_positive


def make_gaussian_policy(
    obs_dim: int,
    act_dim: int,
    *,
    hidden: Sequence[int] = (300, 300),
    init_std: float = 1.0,
    learn_std: bool = True,
    in_keys: Sequence[str] = ("observation",),
    seed: int | None = None,
) -> ProbabilisticActor:
    """Return a Gaussian MLP policy ``π(a|s)`` with a state-independent std.

    Args:
        obs_dim: size of the concatenated ``in_keys`` features.
        act_dim: action size.

    Keyword Args:
        hidden: hidden layer widths (ReLU).
        init_std: initial standard deviation of every action dimension (> 0).
        learn_std: ``False`` keeps the std at ``init_std``: no gradient moves it (:class:`FixedNormalScale`), in
            MAML's inner step, its TRPO step or a meta-test's adaptation. maml_rl's ``MAMLGaussianMLPPolicy`` has
            the same switch (``learn_std=True`` by default, ``sandbox/rocky/tf/policies/
            maml_minimal_gauss_mlp_policy.py`` lines 33 and 110-115: the std parameter's ``trainable``).
        in_keys: observation keys, concatenated along the last dimension.
        seed: draw the weights from ``torch.manual_seed(seed)`` inside a forked RNG (the global RNG is untouched);
            ``None``: from the global RNG, as any torch layer.
    """
    if obs_dim < 1 or act_dim < 1:
        raise ValueError(f"obs_dim and act_dim must be positive, got {obs_dim} and {act_dim}.")
    check_positive("init_std", init_std)
    with torch.random.fork_rng(devices=[]) if seed is not None else contextlib.nullcontext():
        if seed is not None:
            torch.manual_seed(seed)
        mlp = MLP(in_features=obs_dim, out_features=act_dim, num_cells=list(hidden), activation_class=nn.ReLU)
        for layer in mlp.modules():
            if isinstance(layer, nn.Linear):
                nn.init.xavier_uniform_(layer.weight)
                nn.init.zeros_(layer.bias)
    head = AddStateIndependentNormalScale if learn_std else FixedNormalScale
    net = nn.Sequential(mlp, head(act_dim, init_value=math.log(init_std), scale_lb=1e-6))
    module = TensorDictModule(_Concat(net) if len(in_keys) > 1 else net, in_keys=list(in_keys),
                              out_keys=["loc", "scale"])
    if learn_std:  # MAML evaluates every task's parameters in one matmul per layer; a fixed std's tasks by vmap
        declare_batched_layers(module, mlp, net[1])
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=["action"],
        distribution_class=IndependentNormal,
        return_log_prob=True,
        log_prob_key="action_log_prob",
    )


def policy_log_std(policy: nn.Module) -> nn.Parameter:
    """The state-independent log-std ``[act_dim]`` of a :func:`make_gaussian_policy` policy."""
    (scale,) = [m for m in policy.modules() if isinstance(m, AddStateIndependentNormalScale)]
    return scale.state_independent_scale


def std_is_fixed(policy: nn.Module) -> bool:
    """Whether a :func:`make_gaussian_policy` policy was built with ``learn_std=False``."""
    return any(isinstance(m, FixedNormalScale) for m in policy.modules())


class FixedNormalScale(AddStateIndependentNormalScale):
    """An :class:`~tensordict.nn.AddStateIndependentNormalScale` whose log-std no gradient moves.

    The log-std stays a parameter, so the policy's parameter keys and state dict are those of a learned one and
    MAML's per-task parameters, inner step and TRPO step need no special case; it enters the forward as
    ``p + (0 · p)`` with ``p`` detached in the first term, so its value is used and every gradient, of any order,
    with respect to it is exactly zero.
    """

    def forward(self, loc: torch.Tensor, *others: torch.Tensor) -> tuple[torch.Tensor, ...]:
        param = self.state_independent_scale
        scale = (param.detach() + 0 * param).expand_as(loc)
        return (loc, mappings(self.scale_mapping)(scale).clamp_min(self.scale_lb), *others)


class _Concat(nn.Module):
    """Concatenates several inputs on the last dim before calling ``net``."""

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net

    def forward(self, *inputs: torch.Tensor):
        return self.net(torch.cat(inputs, dim=-1))
