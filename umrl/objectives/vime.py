"""VIME's dynamics-model objective, and the reader of the checkpoints written by ``recipes/vime.py``.

:class:`VIMELoss`: the negative ELBO of a Bayesian dynamics network on a buffer of transitions.

Checkpoint format ``"umrl.vime.v1"``: a ``torch.save``'d dict, files ``<output_dir>/checkpoints/step_<iteration>.pt``
(the final one of a run is the latest), with

- ``"format"``: ``"umrl.vime.v1"``;
- ``"meta"``: ``env`` (name), ``obs_dim``, ``act_dim``, ``policy_hidden``, ``policy_init_std``, ``dynamics_hidden``,
  ``prior_std``, ``likelihood_std``;
- ``"policy"``: state dict of :func:`umrl.modules.policy.make_gaussian_policy` ``(obs_dim, act_dim,
  hidden=policy_hidden, init_std=policy_init_std)`` (reads ``"observation"``, writes ``"loc"``, ``"scale"``,
  ``"action"``, ``"action_log_prob"``);
- ``"dynamics"``: state dict of :class:`~umrl.modules.bnn.BayesianDynamics` (posterior and running statistics);
- ``"dynamics_optimizer"``: Adam state; ``"median_history"``: the bonus normaliser's recent medians;
- ``"replay"`` / ``"holdout"``: the dynamics model's transitions (TensorDicts) or ``None``;
- ``"counters"``: ``iteration``, ``frames``; ``"initial_coverage"``: coverage of the untrained policy; ``"visited"``:
  the cells (or velocity range) visited so far;
  ``"rng"``: torch RNG state; ``"config"``: the resolved recipe config (also beside it as ``config.yaml``).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from typing import ClassVar

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.modules import ProbabilisticActor
from torchrl.objectives.common import LossModule

from umrl.modules.bnn import BayesianDynamics
from umrl.modules.policy import make_gaussian_policy
from umrl.runtime import load_checkpoint

FORMAT = "umrl.vime.v1"

__all__ = ["FORMAT", "VIMELoss", "load_vime_checkpoint", "load_vime_dynamics", "load_vime_policy"]


class VIMELoss(LossModule):
    """Bayes-by-backprop loss of VIME's dynamics model.

    Presented in:

        Houthooft et al., "VIME: Variational Information Maximizing Exploration" (2016).
        https://arxiv.org/abs/1605.09674

    ``loss_dynamics = KL(q(theta) || p(theta)) / dataset_size - mean_{n, s} log p(s'_n | s_n, a_n, theta_s)``: the
    negative ELBO per transition of a dataset of ``dataset_size`` transitions (set it to the replay buffer's current
    size before each round of updates), with ``num_samples`` reparameterised weight draws shared by the batch.
    Targets and inputs are standardised by the model's running statistics (update them with
    :meth:`~umrl.modules.bnn.BayesianDynamics.update_normalizer` when data is added, not here).

    Args:
        dynamics (BayesianDynamics): the model; trained in place by whatever optimiser holds its parameters.

    Keyword Args:
        dataset_size (int): ``N`` in the KL weight ``1 / N`` (> 0). Mutable attribute.
        num_samples (int): Monte-Carlo weight samples per forward. Default 10.

    Reads (batch ``[*B]``, flattened): ``"observation"`` ``[*B, D]``, ``"action"`` ``[*B, A]``,
    ``("next", "observation")`` ``[*B, D]``. Returns a TensorDict with ``loss_dynamics`` (differentiable) and the
    detached diagnostics ``kl_prior`` (the full KL, nats), ``log_likelihood`` (mean per transition) and
    ``elbo`` (``-loss_dynamics``).

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from umrl.modules.bnn import BayesianDynamics
        >>> bnn = BayesianDynamics(obs_dim=2, act_dim=2)
        >>> loss = VIMELoss(bnn, dataset_size=128)
        >>> obs, act = torch.randn(128, 2), torch.randn(128, 2)
        >>> td = TensorDict({"observation": obs, "action": act, ("next", "observation"): obs + 0.1 * act}, [128])
        >>> bnn.update_normalizer(obs, act, obs + 0.1 * act)
        >>> out = loss(td)
        >>> out["loss_dynamics"].backward()
        >>> sorted(out.keys())
        ['elbo', 'kl_prior', 'log_likelihood', 'loss_dynamics']
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by the loss (change them with :meth:`set_keys`).

        Attributes:
            observation (NestedKey): state ``s``. Defaults to ``"observation"``.
            action (NestedKey): action ``a``. Defaults to ``"action"``.
            next_observation (NestedKey): next state ``s'``. Defaults to ``("next", "observation")``.
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"
        next_observation: NestedKey = ("next", "observation")

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    out_keys: ClassVar[list[str]] = ["loss_dynamics", "kl_prior", "log_likelihood", "elbo"]

    def __init__(self, dynamics: BayesianDynamics, *, dataset_size: int, num_samples: int = 10):
        super().__init__()
        if dataset_size < 1 or num_samples < 1:
            raise ValueError(f"dataset_size and num_samples must be positive, got {dataset_size} and {num_samples}.")
        self.dynamics = dynamics
        self.dataset_size = int(dataset_size)
        self.num_samples = int(num_samples)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = self.tensor_keys
        return [keys.observation, keys.action, keys.next_observation]

    def log_likelihood(self, tensordict: TensorDictBase) -> torch.Tensor:
        """Mean (over transitions and weight samples) log-likelihood of the batch's next observations, a scalar."""
        obs, action, next_obs = (tensordict.get(k).reshape(-1, tensordict.get(k).shape[-1]) for k in self.in_keys)
        x, y = self.dynamics.normalize(obs, action, next_obs)
        return self.dynamics.log_likelihood(x, y, self.dynamics.sample_noise(self.num_samples)).mean()

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        log_lik = self.log_likelihood(tensordict)
        kl = self.dynamics.kl_to_prior()
        loss = kl / self.dataset_size - log_lik
        return TensorDict(
            {
                "loss_dynamics": loss,
                "kl_prior": kl.detach(),
                "log_likelihood": log_lik.detach(),
                "elbo": -loss.detach(),
            },
            batch_size=[],
        )


def load_vime_checkpoint(path: str | os.PathLike) -> dict:
    """Load a VIME checkpoint: a ``step_*.pt`` file, a ``checkpoints/`` folder or a run's output_dir (latest)."""
    return load_checkpoint(path, format=FORMAT, what="VIME")


def load_vime_policy(path: str | os.PathLike) -> ProbabilisticActor:
    """The VIME-pre-trained 2x300 Gaussian policy (trainable, for fine-tuning; the VIME-init baseline).

    Reads ``"observation"``, writes ``"loc"``, ``"scale"``, ``"action"`` and ``"action_log_prob"``, exactly like
    :func:`umrl.modules.policy.make_gaussian_policy`.
    """
    state = load_vime_checkpoint(path)
    meta = state["meta"]
    policy = make_gaussian_policy(meta["obs_dim"], meta["act_dim"], hidden=meta["policy_hidden"],
                                  init_std=meta["policy_init_std"])
    policy.load_state_dict(state["policy"])
    return policy


def load_vime_dynamics(path: str | os.PathLike) -> BayesianDynamics:
    """The trained Bayesian dynamics model (with its running statistics), e.g. to score transitions."""
    meta = (state := load_vime_checkpoint(path))["meta"]
    dynamics = BayesianDynamics(meta["obs_dim"], meta["act_dim"], hidden=meta["dynamics_hidden"],
                                prior_std=meta["prior_std"], likelihood_std=meta["likelihood_std"])
    dynamics.load_state_dict(state["dynamics"])
    return dynamics
