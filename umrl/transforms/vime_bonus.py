"""VIME's exploration bonus as a TorchRL transform: ``r <- r + eta * info_gain / median(recent info gains)``."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.data import Composite, Unbounded
from torchrl.envs.transforms import Transform

from umrl.modules.bnn import BayesianDynamics
from umrl.validation import check_float

__all__ = ["VIMEBonus"]


class VIMEBonus(Transform):
    """Adds VIME's information-gain bonus to the reward (Houthooft et al., 2016, https://arxiv.org/abs/1605.09674).

    For each transition ``(s, a, s')`` the info gain ``KL`` is
    :meth:`BayesianDynamics.info_gain <umrl.modules.bnn.BayesianDynamics.info_gain>` (one ``vmap(grad)`` for the
    whole batch); the bonus is ``eta * KL / m`` with ``m`` the median of the per-call medians of the last
    ``median_window`` calls, the current one included (VIME's normalisation, which makes ``eta`` scale-free). Set
    the attribute ``update_history = False`` to freeze the history (e.g. to score evaluation data); it is not tied
    to ``train()``/``eval()`` because TorchRL puts every transform appended to an env in eval mode.

    Written under ``"next"``: ``reward_key`` (previous reward + bonus), ``extrinsic_key`` (the reward before the
    bonus: zero for the reward-free CMPs), ``intrinsic_key`` (the bonus) and ``info_gain_key`` (raw KL, nats), each
    ``[*B, 1]``. The model is held by reference: train it with :class:`umrl.objectives.vime.VIMELoss`.

    Two paths, as for :class:`torchrl.envs.transforms.RNDTransform`:

    - in an env (``_step``): every step scores the env batch;
    - ``forward(td)`` on collected data ``[*B]`` (any batch shape, e.g. ``[N, H]``): scores every transition in one
      call, VIME's way (the bonus of a whole batch from the model before it trains on it). The pre-bonus reward is
      read from ``extrinsic_key`` when present, so relabelling twice never adds the bonus twice.

    Args:
        dynamics (BayesianDynamics): the dynamics model.

    Keyword Args:
        eta (float): bonus weight. Default 1e-4.
        num_samples (int): weight samples for the info gain. Default 10.
        median_window (int): number of recent per-call medians kept. Default 10.
        chunk_size (int | None): vmap chunk (see ``info_gain``); ``None`` picks one from the model size.
        reward_key, extrinsic_key, intrinsic_key, info_gain_key (str): keys under ``"next"``. Defaults
            ``"reward"``, ``"extrinsic_reward"``, ``"intrinsic_reward"``, ``"info_gain"``.

    Examples:
        >>> from umrl.envs import make_env
        >>> from umrl.modules.bnn import BayesianDynamics
        >>> env = make_env("point_nav", num_envs=4, seed=0)
        >>> env = env.append_transform(VIMEBonus(BayesianDynamics(2, 2)))
        >>> td = env.rollout(3)
        >>> td["next", "intrinsic_reward"].shape
        torch.Size([4, 3, 1])
    """

    def __init__(
        self,
        dynamics: BayesianDynamics,
        *,
        eta: float = 1e-4,
        num_samples: int = 10,
        median_window: int = 10,
        chunk_size: int | None = None,
        reward_key: str = "reward",
        extrinsic_key: str = "extrinsic_reward",
        intrinsic_key: str = "intrinsic_reward",
        info_gain_key: str = "info_gain",
    ):
        check_float("eta", eta, ge=0)
        if eta < 0 or num_samples < 1 or median_window < 1:
            raise ValueError(
                f"VIMEBonus needs eta >= 0, num_samples >= 1, median_window >= 1; got {eta}, {num_samples}, "
                f"{median_window}."
            )
        super().__init__(in_keys=["observation", "action", ("next", "observation")],
                         out_keys=[reward_key, extrinsic_key, intrinsic_key, info_gain_key])
        self.dynamics = dynamics
        self.eta = float(eta)
        self.num_samples = int(num_samples)
        self.chunk_size = chunk_size
        self.update_history = True
        self.reward_key, self.extrinsic_key = reward_key, extrinsic_key
        self.intrinsic_key, self.info_gain_key = intrinsic_key, info_gain_key
        self.register_buffer("median_history", torch.full((median_window,), float("nan")))

    def bonus(self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(bonus, info_gain)`` for transitions ``[*B, D]``, ``[*B, A]``, ``[*B, D]`` -> two ``[*B, 1]`` tensors."""
        batch = obs.shape[:-1]
        kl = self.dynamics.info_gain(
            obs.reshape(-1, obs.shape[-1]), action.reshape(-1, action.shape[-1]),
            next_obs.reshape(-1, next_obs.shape[-1]), num_samples=self.num_samples, chunk_size=self.chunk_size,
        ).detach()
        current = kl.median()
        if self.update_history:
            self.median_history.copy_(torch.cat([self.median_history[1:], current.reshape(1)]))
        history = self.median_history[~self.median_history.isnan()]
        scale = history.median() if history.numel() else current
        bonus = self.eta * kl / scale.clamp_min(1e-12)
        return bonus.reshape(*batch, 1), kl.reshape(*batch, 1)

    def _write(self, next_td: TensorDictBase, obs, action, next_obs) -> TensorDictBase:
        base = next_td.get(self.extrinsic_key, None)
        if base is None:
            base = next_td.get(self.reward_key)
        bonus, kl = self.bonus(obs, action, next_obs)
        next_td.set(self.extrinsic_key, base)
        next_td.set(self.intrinsic_key, bonus)
        next_td.set(self.info_gain_key, kl)
        next_td.set(self.reward_key, base + bonus)
        return next_td

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        return self._write(next_tensordict, tensordict.get("observation"), tensordict.get("action"),
                           next_tensordict.get("observation"))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        """Scores (relabels) a batch of collected transitions in place; returns it."""
        self._write(tensordict.get("next"), tensordict.get("observation"), tensordict.get("action"),
                    tensordict.get(("next", "observation")))
        return tensordict

    def transform_reward_spec(self, reward_spec: Composite) -> Composite:
        spec = reward_spec[self.reward_key]
        for key in (self.extrinsic_key, self.intrinsic_key, self.info_gain_key):
            reward_spec[key] = Unbounded(shape=spec.shape, dtype=torch.float32, device=spec.device)
        return reward_spec
