"""Vanilla policy gradient on batches of per-task trajectories: mask, linear feature baseline, GAE, surrogate.

Every function works on a TensorDict (or tensors) whose batch shape ends with ``[..., N, H]``: any leading dims
(typically ``[T]`` tasks) are independent problems, ``N`` trajectories of ``H`` steps each, as returned by
:func:`umrl.rollout.collect`. Keys read: ``"observation"`` ``[..., N, H, obs_dim]``, ``"step_count"``
``[..., N, H, 1]``, ``("next", "reward")`` / ``("next", "done")`` ``[..., N, H, 1]`` and ``"mask"`` ``[..., N, H]``.

Trajectories end at their first ``done``; the steps a batched env takes after that (it auto-resets) are masked out.
The baseline regresses the discounted return-to-go of the *finite-horizon* problem on features that include time,
so the value after the horizon is zero by definition: a time-limit ``done`` is a true end here (no bootstrap),
exactly like rllab's ``LinearFeatureBaseline`` + GAE that MAML-RL used.

Example (point_nav's oracle goals as tasks):
    >>> import torch
    >>> from umrl.modules.policy import make_gaussian_policy
    >>> from umrl.objectives.policy_gradient import compute_advantages
    >>> from umrl.proposals import make_proposal
    >>> from umrl.rollout import collect
    >>> T, N, H = 2, 3, 5                                             # tasks, trajectories per task, horizon
    >>> proposal = make_proposal("oracle", "point_nav", num_tasks=T, trajectories_per_task=N, horizon=H)
    >>> goals = proposal.resample(torch.Generator().manual_seed(0))   # [T, 2]
    >>> policy = make_gaussian_policy(2, 2, hidden=[16])
    >>> td = collect(proposal.env, policy, num_tasks=T, horizon=H)  # [T, N, H]
    >>> td = compute_advantages(td, gamma=0.99, lmbda=1.0)        # adds "state_value", "value_target", "advantage"
    >>> log_prob = policy.get_dist(td).log_prob(td["action"])     # [T, N, H]
    >>> loss = vpg_loss(log_prob, td)                             # [T]: one loss per task
    >>> loss.shape
    torch.Size([2])
"""
from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torchrl.objectives.value.functional import vec_generalized_advantage_estimate

from umrl.process import torch_threads
from umrl.trajectories import trajectory_mask

#: TorchRL's fast GAE drops the terms of its ``(γλ)^k`` series below this threshold (its ``thr``); with ``γλ`` below
#: it no term is left and it fails (``IndexError``), although the estimate is then the one-step TD error.
_GAE_SERIES_THRESHOLD = 1e-7

__all__ = [
    "baseline_features",
    "compute_advantages",
    "episode_lengths",
    "episode_mean",
    "episode_returns",
    "fit_linear_baseline",
    "trajectory_mask",
    "vpg_loss",
]


def baseline_features(td: TensorDictBase, *, time_scale: float = 100.0, obs_clip: float = 10.0,
                      observation_key: NestedKey = "observation", step_count_key: NestedKey = "step_count",
                      ) -> torch.Tensor:
    """Features ``(o, o², t, t², t³, 1)`` of shape ``[..., N, H, 2 * obs_dim + 4]`` (rllab's linear baseline).

    ``o`` is the observation (``td[observation_key]``) clipped to ``±obs_clip``; ``t = step_count / time_scale``
    (``td[step_count_key]``).
    """
    obs = td.get(observation_key).clamp(-obs_clip, obs_clip)
    t = td.get(step_count_key).to(obs.dtype) / time_scale
    return torch.cat([obs, obs.pow(2), t, t.pow(2), t.pow(3), torch.ones_like(t)], dim=-1)


def fit_linear_baseline(
    features: torch.Tensor,
    targets: torch.Tensor,
    mask: torch.Tensor,
    *,
    reg_coeff: float = 1e-5,
    max_tries: int = 5,
) -> torch.Tensor:
    """Ridge least squares of ``targets`` on ``features``, one fit per leading index, over all valid ``N × H`` steps.

    Solved in float64 from the normal equations ``(XᵀX + c I) w = Xᵀy``; if the solution is not finite the ridge
    ``c`` grows ×10 (at most ``max_tries`` times) and then a ``FloatingPointError`` is raised — never a silent
    garbage baseline. On the CPU the solve runs on one torch thread: torch 2.13's multi-threaded LU (oneMKL) returns
    wrong solutions or fails ("Parameter 6 was incorrect on entry to DLASWP") from about 150 features (ant's 214) on
    an AMD EPYC, and one thread is what every committed run used.

    Args:
        features: ``[..., N, H, F]``.
        targets: ``[..., N, H, 1]`` (discounted returns-to-go).
        mask: ``[..., N, H]`` bool, the steps to fit.

    Returns:
        fitted values ``[..., N, H, 1]`` (same dtype as ``features``).
    """
    if features.shape[:-1] != targets.shape[:-1] or features.shape[:-1] != mask.shape:
        raise ValueError(
            f"shape mismatch: features {tuple(features.shape)}, targets {tuple(targets.shape)}, mask {tuple(mask.shape)}"
            " must share [..., N, H]."
        )
    lead = features.shape[:-3]
    num_features = features.shape[-1]
    w_mask = mask.unsqueeze(-1).to(torch.float64)
    x = (features.to(torch.float64) * w_mask).reshape(*lead, -1, num_features)
    y = (targets.to(torch.float64) * w_mask).reshape(*lead, -1, 1)
    xtx = x.transpose(-1, -2) @ x
    xty = x.transpose(-1, -2) @ y
    eye = torch.eye(num_features, dtype=torch.float64, device=x.device)
    coeff = reg_coeff
    for _ in range(max_tries):
        with torch_threads(1 if x.device.type == "cpu" else None):
            weights = torch.linalg.solve(xtx + coeff * eye, xty)
        if torch.isfinite(weights).all():
            return (features.to(torch.float64) @ weights.unsqueeze(-3)).to(features.dtype)
        coeff *= 10
    raise FloatingPointError(
        f"linear baseline fit is not finite even with ridge {coeff / 10:g}: the observations or rewards contain "
        "NaN/inf or are enormous; check the env and the reward transform."
    )


def _gae(
    gamma: float, lmbda: float, values: torch.Tensor, next_values: torch.Tensor, reward: torch.Tensor,
    ends: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``(advantage, value_target)`` of TorchRL's vectorised GAE over ``[..., H, 1]`` tensors (time on dim -2);
    ``ends`` marks the steps after which nothing is bootstrapped.

    With ``γλ`` under ``_GAE_SERIES_THRESHOLD`` (``gamma=0`` or ``lmbda=0``) the advantage is the one-step TD
    error ``r + γ V(s') - V(s)`` (``r - V(s)`` for ``gamma=0``), computed here: TorchRL's scalar path fails on it.
    """
    if gamma * lmbda < _GAE_SERIES_THRESHOLD:
        advantage = reward + gamma * (~ends) * next_values - values
        return advantage, advantage + values
    return vec_generalized_advantage_estimate(gamma, lmbda, values, next_values, reward, ends, ends, time_dim=-2)


def compute_advantages(
    td: TensorDictBase,
    *,
    gamma: float = 0.99,
    lmbda: float = 1.0,
    normalize: bool = True,
    reg_coeff: float = 1e-5,
    time_scale: float = 100.0,
    observation_key: NestedKey = "observation",
    step_count_key: NestedKey = "step_count",
    reward_key: NestedKey = "reward",
    done_key: NestedKey = "done",
    mask_key: NestedKey = "mask",
    advantage_key: NestedKey = "advantage",
    value_target_key: NestedKey = "value_target",
    value_key: NestedKey = "state_value",
) -> TensorDictBase:
    """Fit the linear feature baseline and write GAE advantages, in place.

    Reads ``"observation"``, ``"step_count"``, ``("next", "reward")``, ``("next", "done")`` and ``"mask"`` (computed
    from ``done`` and written if absent). Writes ``"value_target"`` (discounted return-to-go), ``"state_value"``
    (baseline) and ``"advantage"``, each ``[..., N, H, 1]`` and zero on masked steps. With ``normalize`` the
    advantages of each leading index are standardised over its valid steps (rllab's ``center_adv``). The ``*_key``
    arguments rename each of these entries (``reward_key`` and ``done_key`` under ``"next"``, as in TorchRL's value
    estimators).
    """
    if td.batch_dims < 2:
        raise ValueError(f"expected a batch [..., N, H] of trajectories, got batch size {tuple(td.batch_size)}.")
    done = td.get(("next", done_key))
    mask = td.get(mask_key, None)
    if mask is None:
        mask = trajectory_mask(done)
        td.set(mask_key, mask)
    valid = mask.unsqueeze(-1)
    reward = td.get(("next", reward_key)) * valid
    # the first episode ends at its done; the masked steps after it (zero reward, zero value) run as one segment to the
    # row's end: TorchRL's GAE pads every segment to the longest, so one segment per masked step (their own done or
    # not) cost up to H x the batch (over 24 GB + 24 GB of swap for point_nav's oracle with one-step episodes)
    row_end = torch.zeros_like(valid)
    row_end[..., -1, :] = True
    ends = (done & valid) | (~valid & row_end)
    zeros = torch.zeros_like(reward)
    _, returns = _gae(gamma, 1.0, zeros, zeros, reward, ends)
    features = baseline_features(td, time_scale=time_scale, observation_key=observation_key,
                                 step_count_key=step_count_key)
    values = fit_linear_baseline(features, returns, mask, reg_coeff=reg_coeff) * valid
    next_values = torch.cat([values[..., 1:, :], torch.zeros_like(values[..., :1, :])], dim=-2)
    advantage, _ = _gae(gamma, lmbda, values, next_values, reward, ends)
    advantage = advantage * valid
    if normalize:
        dims = tuple(range(-3, 0))
        count = valid.sum(dims, keepdim=True).clamp_min(1)
        mean = advantage.sum(dims, keepdim=True) / count
        var = ((advantage - mean).pow(2) * valid).sum(dims, keepdim=True) / count
        advantage = (advantage - mean) / (var.sqrt() + 1e-8) * valid
    td.set(value_target_key, returns * valid)
    td.set(value_key, values)
    td.set(advantage_key, advantage)
    return td


def vpg_loss(
    log_prob: torch.Tensor, td: TensorDictBase, *, advantage_key: NestedKey = "advantage", mask_key: NestedKey = "mask"
) -> torch.Tensor:
    """Vanilla policy-gradient surrogate ``−mean_valid(log π(a|s) · A)`` per leading index.

    Args:
        log_prob: ``[..., N, H]`` log-probabilities of ``td["action"]`` under the policy being differentiated.
        td: batch ``[..., N, H]`` with the advantage ``[..., N, H, 1]`` and the mask ``[..., N, H]``.

    Keyword Args:
        advantage_key, mask_key: where ``td`` holds them (``"advantage"``, ``"mask"``).

    Returns:
        ``[...]`` — e.g. one loss per task for a ``[T, N, H]`` batch (a scalar for ``[N, H]``).
    """
    mask = td[mask_key]
    if log_prob.shape != mask.shape:
        raise ValueError(f"log_prob has shape {tuple(log_prob.shape)}, expected the batch's [..., N, H] {tuple(mask.shape)}.")
    weights = mask.to(log_prob.dtype)
    return -(log_prob * td[advantage_key].squeeze(-1) * weights).sum((-2, -1)) / weights.sum((-2, -1)).clamp_min(1)


def _first_episode(td: TensorDictBase) -> torch.Tensor:
    return td["mask"] if "mask" in td else trajectory_mask(td["next", "done"])


def episode_returns(td: TensorDictBase) -> torch.Tensor:
    """Undiscounted return of each trajectory's first episode, ``[..., N]``."""
    return (td["next", "reward"].squeeze(-1) * _first_episode(td)).sum(-1)


def episode_lengths(td: TensorDictBase) -> torch.Tensor:
    """Steps in each trajectory's first episode, ``[..., N]`` (long): the horizon unless the env ended it earlier."""
    return _first_episode(td).sum(-1)


def episode_mean(values: torch.Tensor, td: TensorDictBase) -> torch.Tensor:
    """Mean of per-trajectory ``values`` ``[..., N]`` over the trajectories that hold an episode, ``[...]``.

    Every trajectory of a fixed-trajectory batch does; a batch of fixed env steps
    (:func:`umrl.rollout.collect_env_steps`) pads the tasks that need fewer episodes with empty ones, which this
    leaves out (the reference's ``AverageReturn`` over the paths it sampled).
    """
    held = _first_episode(td).any(-1)
    return (values * held).sum(-1) / held.sum(-1).clamp_min(1)
