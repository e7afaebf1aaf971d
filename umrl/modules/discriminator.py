"""Skill discriminator D(z|s): an MLP from the observation (or chosen dims of it) to logits over K skills."""
from __future__ import annotations

import contextlib
from collections.abc import Sequence

import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictModuleBase
from torchrl.modules import MLP

__all__ = ["DISCRIMINATOR_INITS", "ObservationDims", "discriminator_logits", "make_discriminator"]

#: ``"xavier"``: Glorot-uniform weights, zero biases, as the DIAYN reference code initialises every MLP
#: (haarnoja/sac ``sac/misc/mlp.py``: ``tf.contrib.layers.xavier_initializer()`` weights,
#: ``tf.constant_initializer(0.)`` biases). ``"torch"``: ``torch.nn.Linear``'s default (Kaiming-uniform weights with
#: a = sqrt(5), i.e. U(+-1/sqrt(fan_in)), and U(+-1/sqrt(fan_in)) biases).
DISCRIMINATOR_INITS = ("xavier", "torch")


class ObservationDims(torch.nn.Module):
    """Keeps the observation dims ``dims`` (last axis): ``[*B, obs_dim] -> [*B, len(dims)]``.

    In front of a discriminator it is DIAYN's "prior" variant (Eysenbach et al., 2018, "using prior knowledge": the
    discriminator sees only chosen state dims, e.g. the x-y position), not the unsupervised method, which sees the
    whole observation.
    """

    def __init__(self, dims: Sequence[int]):
        super().__init__()
        self.register_buffer("dims", torch.as_tensor(list(dims), dtype=torch.long), persistent=False)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        return observation.index_select(-1, self.dims)


def make_discriminator(
    obs_dim: int,
    num_skills: int,
    *,
    hidden: Sequence[int] = (300, 300),
    seed: int | None = None,
    init: str = "xavier",
    input_dims: Sequence[int] | None = None,
    in_key="observation",
    out_key="skill_logits",
) -> TensorDictModule:
    """Builds D(z|s) as a ReLU MLP ``obs_dim -> hidden -> num_skills``.

    Args:
        obs_dim (int): observation size.
        num_skills (int): K >= 2, the number of logits.

    Keyword Args:
        hidden (sequence of int): hidden layer widths. Defaults to ``(300, 300)`` (docs/protocol.md).
        seed (int, optional): if given, the weights are initialised from ``torch.manual_seed(seed)`` inside a forked
            RNG (the global RNG is untouched), so a frozen random discriminator (UML-random) is reproducible.
        init (str): weight initialisation, one of :data:`DISCRIMINATOR_INITS`. Defaults to ``"xavier"`` (the DIAYN
            reference code's: Glorot-uniform weights U(+-sqrt(6 / (fan_in + fan_out))), zero biases); ``"torch"``
            keeps ``torch.nn.Linear``'s default.
        input_dims (sequence of int, optional): the observation dims D reads (:class:`ObservationDims`, DIAYN's
            "prior" variant; an ablation, not the paper's method). Defaults to ``None``: the whole observation.
        in_key / out_key: tensordict keys. Defaults to ``"observation"`` -> ``"skill_logits"`` [*B, K].

    Returns:
        a :class:`~tensordict.nn.TensorDictModule` reading ``in_key`` [*B, obs_dim], writing ``out_key`` [*B, K].

    Examples:
        >>> from tensordict import TensorDict
        >>> d = make_discriminator(2, 50, seed=0).requires_grad_(False)  # a frozen random discriminator
        >>> d(TensorDict({"observation": torch.zeros(3, 2)}, [3]))["skill_logits"].shape
        torch.Size([3, 50])
    """
    if obs_dim < 1:
        raise ValueError(f"obs_dim must be >= 1, got {obs_dim}.")
    if num_skills < 2:
        raise ValueError(f"num_skills must be >= 2, got {num_skills}.")
    if init not in DISCRIMINATOR_INITS:
        raise ValueError(f"init must be one of {DISCRIMINATOR_INITS}, got {init!r}.")
    if input_dims is not None and (
        not input_dims or len(set(input_dims)) != len(input_dims) or not all(0 <= d < obs_dim for d in input_dims)
    ):
        raise ValueError(f"input_dims must be distinct observation dims in [0, {obs_dim}), got {list(input_dims)}.")
    # Seeded: draw the weights from a forked RNG; unseeded: consume the global RNG as any torch layer does.
    with torch.random.fork_rng(devices=[]) if seed is not None else contextlib.nullcontext():
        if seed is not None:
            torch.manual_seed(seed)
        net = MLP(
            in_features=obs_dim if input_dims is None else len(input_dims),
            out_features=num_skills,
            num_cells=list(hidden),
            activation_class=torch.nn.ReLU,
        )
        if init == "xavier":
            for layer in net.modules():
                if isinstance(layer, torch.nn.Linear):
                    torch.nn.init.xavier_uniform_(layer.weight)
                    torch.nn.init.zeros_(layer.bias)
    if input_dims is not None:
        net = torch.nn.Sequential(ObservationDims(input_dims), net)
    return TensorDictModule(net, in_keys=[in_key], out_keys=[out_key])


def discriminator_logits(discriminator: TensorDictModuleBase, observation: torch.Tensor) -> torch.Tensor:
    """D's logits ``[*B, K]`` for observations ``[*B, obs_dim]`` (D reads one key and writes one, as
    :func:`make_discriminator`'s module does); gradients flow unless the caller disables them."""
    td = TensorDict({discriminator.in_keys[0]: observation}, batch_size=observation.shape[:-1])
    return discriminator(td).get(discriminator.out_keys[0])
