"""Skill-conditioned SAC networks: a tanh-Gaussian actor pi(a|s,z) and Q(s,z,a) for TorchRL's ``SACLoss``.

Both read the observation and the one-hot skill as separate keys; TorchRL's :class:`~torchrl.modules.MLP`
concatenates its inputs on the last dim (``CatTensors``-style), so the skill is never packed into the observation.

Keys (batch shape ``*B``): ``"observation"`` [*B, obs_dim], ``"skill"`` [*B, K] -> actor writes ``"loc"``,
``"scale"`` (and the raw ``"params"``), ``"action"`` [*B, act_dim] in (-1, 1) and ``"action_log_prob"`` [*B]; the Q-network reads
observation, skill and action and writes ``"state_action_value"`` [*B, 1]. ``SACLoss`` makes the twin copies of the
Q-network (``num_qvalue_nets=2``), so one is built here.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictSequential
from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator

__all__ = ["make_skill_actor", "make_skill_qvalue"]


def _check_dims(**dims: int) -> None:
    bad = {name: value for name, value in dims.items() if value < 1}
    if bad:
        raise ValueError(f"dimensions must be positive, got {bad}.")


def make_skill_actor(
    obs_dim: int,
    num_skills: int,
    act_dim: int,
    *,
    hidden: Sequence[int] = (300, 300),
    observation_key="observation",
    skill_key="skill",
) -> ProbabilisticActor:
    """pi(a|s,z): ReLU MLP over ``[observation, skill]`` -> (loc, scale) of a TanhNormal on [-1, 1]^act_dim.

    Examples:
        >>> from tensordict import TensorDict
        >>> actor = make_skill_actor(2, 5, 2, hidden=(32,))
        >>> td = TensorDict({"observation": torch.zeros(3, 2), "skill": torch.eye(5)[:3]}, [3])
        >>> actor(td)["action"].shape, td["action_log_prob"].shape
        (torch.Size([3, 2]), torch.Size([3]))
    """
    _check_dims(obs_dim=obs_dim, num_skills=num_skills, act_dim=act_dim)
    mlp = MLP(in_features=obs_dim + num_skills, out_features=2 * act_dim, num_cells=list(hidden),
              activation_class=torch.nn.ReLU)
    module = TensorDictSequential(
        TensorDictModule(mlp, in_keys=[observation_key, skill_key], out_keys=["params"]),
        TensorDictModule(NormalParamExtractor(), in_keys=["params"], out_keys=["loc", "scale"]),
    )
    return ProbabilisticActor(
        module,
        in_keys=["loc", "scale"],
        out_keys=["action"],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": -1.0, "high": 1.0},
        return_log_prob=True,
        log_prob_key="action_log_prob",
    )


def make_skill_qvalue(
    obs_dim: int,
    num_skills: int,
    act_dim: int,
    *,
    hidden: Sequence[int] = (300, 300),
    observation_key="observation",
    skill_key="skill",
) -> ValueOperator:
    """Q(s,z,a): ReLU MLP over ``[observation, skill, action]`` -> ``"state_action_value"`` [*B, 1]."""
    _check_dims(obs_dim=obs_dim, num_skills=num_skills, act_dim=act_dim)
    net = MLP(in_features=obs_dim + num_skills + act_dim, out_features=1, num_cells=list(hidden),
              activation_class=torch.nn.ReLU)
    return ValueOperator(net, in_keys=[observation_key, skill_key, "action"])
