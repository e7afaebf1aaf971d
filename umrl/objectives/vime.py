"""VIME's dynamics-model objective: :class:`VIMELoss`, the negative ELBO of a Bayesian dynamics network on a buffer
of transitions. The checkpoints of ``recipes/vime.py`` are read by :mod:`umrl.checkpoints.vime`.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives.common import LossModule
from torchrl.objectives.value import ValueEstimatorBase

from umrl.modules.bnn import BayesianDynamics

__all__ = ["VIMELoss"]


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

    def __init__(self, dynamics: BayesianDynamics, *, dataset_size: int, num_samples: int = 10):
        super().__init__()
        if dataset_size < 1 or num_samples < 1:
            raise ValueError(f"dataset_size and num_samples must be positive, got {dataset_size} and {num_samples}.")
        self.out_keys = [  # an instance list: select_out_keys on one loss leaves the others alone
            "loss_dynamics", "kl_prior", "log_likelihood", "elbo"]
        self.dynamics = dynamics
        self.dataset_size = int(dataset_size)
        self.num_samples = int(num_samples)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    def make_value_estimator(self, value_type=None, **hyperparams) -> VIMELoss:
        """Set :attr:`value_estimator` and return the loss.

        The dynamics ELBO needs no value estimate, so this loss's default (``value_type`` None, its
        ``default_value_estimator``) is no estimator: :attr:`value_estimator` is None. As in TorchRL's
        :meth:`~torchrl.objectives.LossModule.make_value_estimator`, a
        :class:`~torchrl.objectives.value.ValueEstimatorBase` instance is attached as given and a subclass is built
        with ``hyperparams``. A :class:`~torchrl.objectives.utils.ValueEstimators` member or any other value, or
        hyperparameters for the default, raise ``ValueError``.
        """
        if value_type is None:
            hyperparams.pop("device", None)  # TorchRL's default construction passes it
            if hyperparams:
                raise ValueError(f"hyperparams: got {sorted(hyperparams)}; VIMELoss's default is no value estimator, "
                                 "which takes none.")
            self._value_estimator = None
            self.value_type = None
            return self
        if isinstance(value_type, ValueEstimatorBase) or (
                isinstance(value_type, type) and issubclass(value_type, ValueEstimatorBase)):
            return super().make_value_estimator(value_type, **hyperparams)
        raise ValueError(f"value_type: got {value_type!r}; expected None (VIMELoss uses no value estimator) or a "
                         "torchrl ValueEstimatorBase instance or subclass.")

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

