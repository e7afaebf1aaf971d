"""VIME pre-training: TRPO on the information-gain bonus alone (the VIME-init baseline's policy).

    python recipes/vime.py env.name=point_nav                     # 30 iterations of 40 x 100 steps
    python recipes/vime.py env.name=half_cheetah logger.backend=csv
    python recipes/vime.py env.name=point_nav resume=true         # continue from the latest checkpoint

Each iteration: collect ``env.num_envs`` trajectories of ``env.horizon`` steps with the current policy
(:func:`umrl.rollout.collect`, one batched policy call per step) -> score every transition with
:class:`~umrl.transforms.vime_bonus.VIMEBonus` using the dynamics model *before* it sees them (the reward is the bonus
alone: the CMP's reward is zero) -> add them to the dynamics model's replay (a share goes to a held-out set) ->
update the running input/target statistics and train the model (:class:`~umrl.objectives.vime.VIMELoss`, Adam) ->
one TRPO step (:class:`umrl.optim.trpo.TRPOStep`) on the importance-ratio surrogate with linear-baseline GAE
advantages (:func:`umrl.objectives.policy_gradient.compute_advantages`).

Logged (namespaced): ``bonus/`` info gain and bonus statistics; ``dynamics/`` training loss, log-likelihood, KL to
the prior, held-out log-likelihood and ELBO per transition; ``trpo/`` improvement, KL, acceptance, backtracks;
``coverage/`` of the batch's visited states (x-y cells and their area for point_nav and ant, velocity ranges for
half_cheetah), the untrained policy's under ``coverage/initial_*`` and everything visited so far under
``coverage/cumulative_*``; ``time/`` env steps/s and seconds per phase.

Checkpoints: ``<output_dir>/checkpoints/step_<iteration>.pt``, format ``umrl.vime.v1`` (documented in
:mod:`umrl.checkpoints.vime`); ``umrl.checkpoints.load_vime_policy(path)`` returns the policy to fine-tune.
``resume=true`` restores the policy, the dynamics model and its optimiser, the bonus normaliser, the transitions,
the counters and the RNG.
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import hydra
import torch
import tqdm
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase

from umrl.checkpoints import VIME_FORMAT, save_vime_checkpoint
from umrl.envs import make_env
from umrl.modules.bnn import BayesianDynamics
from umrl.modules.policy import make_gaussian_policy
from umrl.objectives.policy_gradient import compute_advantages
from umrl.objectives.vime import VIMELoss
from umrl.optim.trpo import TRPOStep
from umrl.rollout import FunctionalPolicy, collect
from umrl.runtime import Checkpointer, check_finite, log_metrics, make_logger, seed_everything
from umrl.transforms.vime_bonus import VIMEBonus

COVERAGE_KEYS = {"point_nav": "position", "ant": "xy_position", "half_cheetah": "x_velocity"}
DEFAULT_CELL = {"point_nav": 0.1, "ant": 0.25}
TRANSITION_KEYS = ("observation", "action", ("next", "observation"))


def state_coverage(batch: TensorDictBase, env_name: str, cell_size: float | None = None) -> dict[str, float]:
    """Coverage of the states visited in ``batch`` (valid steps of ``("next", key)``, ``"mask"`` [..., H]).

    x-y envs: ``cells`` (distinct grid cells of side ``cell_size``), ``area`` (cells x cell area), ``max_distance``
    from the origin. half_cheetah: ``velocity_range`` (max - min forward velocity) and ``velocity_range_p5_p95``.
    """
    values = visited_states(batch, env_name)
    if env_name == "half_cheetah":
        v = values.reshape(-1)
        low, high = torch.quantile(v, torch.tensor([0.05, 0.95]))
        return {"velocity_range": float(v.max() - v.min()), "velocity_range_p5_p95": float(high - low)}
    cell = cell_size if cell_size is not None else DEFAULT_CELL[env_name]
    cells = torch.unique(torch.floor(values / cell).long(), dim=0).shape[0]
    return {"cells": float(cells), "area": cells * cell**2, "max_distance": float(values.norm(dim=-1).max())}


def visited_states(batch: TensorDictBase, env_name: str) -> torch.Tensor:
    """``[M, k]`` x-y positions (point_nav, ant) or forward velocities (half_cheetah) at the batch's valid steps."""
    if env_name not in COVERAGE_KEYS:
        raise ValueError(f"no coverage measure for env {env_name!r}; valid choices: {sorted(COVERAGE_KEYS)}.")
    return batch["next", COVERAGE_KEYS[env_name]][batch["mask"]]


def cumulative_coverage(
    seen: torch.Tensor | None, batch: TensorDictBase, env_name: str, cell_size: float | None = None
) -> tuple[torch.Tensor, dict[str, float]]:
    """Fold ``batch`` into everything visited so far: ``seen`` is the set of visited cells ``[M, 2]`` (x-y envs) or
    the ``[min, max]`` velocity (half_cheetah). Returns the new ``seen`` and ``cumulative_cells`` / ``_area`` or
    ``cumulative_velocity_range``."""
    values = visited_states(batch, env_name)
    if env_name == "half_cheetah":
        v = values.reshape(-1)
        seen = torch.stack([v.min(), v.max()]) if seen is None else torch.stack(
            [torch.minimum(seen[0], v.min()), torch.maximum(seen[1], v.max())])
        return seen, {"cumulative_velocity_range": float(seen[1] - seen[0])}
    cell = cell_size if cell_size is not None else DEFAULT_CELL[env_name]
    cells = torch.floor(values / cell).long()
    seen = torch.unique(cells if seen is None else torch.cat([seen, cells]), dim=0)
    return seen, {"cumulative_cells": float(seen.shape[0]), "cumulative_area": seen.shape[0] * cell**2}


def check_config(cfg: DictConfig) -> None:
    positive = {
        "iterations": cfg.iterations, "env.num_envs": cfg.env.num_envs, "env.horizon": cfg.env.horizon,
        "dynamics.batch_size": cfg.dynamics.batch_size, "dynamics.replay_size": cfg.dynamics.replay_size,
        "dynamics.holdout_size": cfg.dynamics.holdout_size, "dynamics.lr": cfg.dynamics.lr,
        "checkpoint.every": cfg.checkpoint.every,
    }
    bad = {name: value for name, value in positive.items() if not value > 0}
    if bad:
        raise ValueError(f"these config values must be positive: {bad}.")
    if not 0 < cfg.dynamics.holdout_fraction < 1:
        raise ValueError(f"dynamics.holdout_fraction must be in (0, 1), got {cfg.dynamics.holdout_fraction}.")


def append(buffer: TensorDictBase | None, data: TensorDictBase, size: int) -> TensorDictBase:
    """FIFO buffer of transitions: ``buffer`` + ``data``, keeping the newest ``size``."""
    merged = data if buffer is None else torch.cat([buffer, data])
    return merged[-size:]


def trpo_update(trpo: TRPOStep, policy, params: TensorDictBase, batch: TensorDictBase) -> dict[str, float]:
    """One TRPO step on ``-mean(ratio * advantage)`` with the mean KL(old || new) over the valid steps."""
    functional = FunctionalPolicy(policy)
    old = policy.build_dist_from_params(batch.select("loc", "scale"))
    old_log_prob = batch["action_log_prob"]
    weights = batch["mask"].to(old_log_prob.dtype)
    weights = weights / weights.sum()
    advantage = batch["advantage"].squeeze(-1)

    def closure():
        new = functional.dist(params, batch)
        ratio = torch.exp(new.log_prob(batch["action"]) - old_log_prob)
        surrogate = -(ratio * advantage * weights).sum()
        kl = (torch.distributions.kl_divergence(old, new) * weights).sum()
        return surrogate, kl

    return trpo(closure)


def train_dynamics(loss_fn: VIMELoss, optimizer, replay: TensorDictBase, cfg: DictConfig) -> dict[str, float]:
    """``updates_per_iteration`` Adam steps on random minibatches of the replay; mean diagnostics."""
    loss_fn.dataset_size = replay.shape[0]
    logs = []
    for _ in range(cfg.dynamics.updates_per_iteration):
        out = loss_fn(replay[torch.randint(replay.shape[0], (cfg.dynamics.batch_size,))])
        check_finite({"loss_dynamics": out["loss_dynamics"]}, "dynamics update")
        optimizer.zero_grad(set_to_none=True)
        out["loss_dynamics"].backward()
        optimizer.step()
        logs.append(out.detach())
    if not logs:
        return {}
    mean = torch.stack(logs).mean()
    return {"loss": float(mean["loss_dynamics"]), "log_likelihood": float(mean["log_likelihood"]),
            "kl_prior": float(mean["kl_prior"])}


@torch.no_grad()
def heldout_metrics(loss_fn: VIMELoss, holdout: TensorDictBase) -> dict[str, float]:
    """Log-likelihood and ELBO per transition on held-out transitions (KL weighted by the training set size)."""
    log_lik = loss_fn.log_likelihood(holdout).item()
    elbo = log_lik - loss_fn.dynamics.kl_to_prior().item() / loss_fn.dataset_size
    return {"heldout_log_likelihood": log_lik, "heldout_elbo": elbo}


def plot_coverage(first: TensorDictBase, last: TensorDictBase, env_name: str, path: Path) -> None:
    """Visited x-y positions of the untrained policy's batch and of the last batch (2-D envs)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 5))
    for batch, label, color in ((first, "initial policy", "tab:gray"), (last, "VIME policy", "tab:red")):
        xy = batch["next", COVERAGE_KEYS[env_name]][batch["mask"]]
        ax.scatter(xy[:, 0], xy[:, 1], s=1, alpha=0.3, color=color, label=label)
    ax.set_aspect("equal")
    ax.legend(markerscale=8)
    ax.set_title(f"VIME {env_name}: visited states")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def train(cfg: DictConfig) -> dict:
    """Run VIME pre-training as configured; return the last metrics and the checkpoint path."""
    check_config(cfg)
    seed_everything(cfg.seed)
    out_dir = Path(cfg.output_dir)
    checkpointer = Checkpointer(out_dir / "checkpoints", keep_all=cfg.checkpoint.keep_all)

    env = make_env(cfg.env.name, cfg.env.num_envs, seed=cfg.seed, device=cfg.device, horizon=cfg.env.horizon,
                   backend=cfg.env.backend)
    obs_dim, act_dim = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    policy = make_gaussian_policy(obs_dim, act_dim, hidden=list(cfg.policy.hidden), init_std=cfg.policy.init_std)
    dyn = cfg.dynamics
    dynamics = BayesianDynamics(obs_dim, act_dim, hidden=list(dyn.hidden), prior_std=dyn.prior_std,
                                likelihood_std=dyn.likelihood_std, init_std=dyn.init_std)
    loss_fn = VIMELoss(dynamics, dataset_size=1, num_samples=dyn.num_samples)
    optimizer = torch.optim.Adam(dynamics.parameters(), lr=dyn.lr)
    bonus = VIMEBonus(dynamics, eta=cfg.bonus.eta, num_samples=cfg.bonus.num_samples,
                      median_window=cfg.bonus.median_window)
    params = TensorDict.from_module(policy)
    t = cfg.trpo
    trpo = TRPOStep(params, max_kl=t.max_kl, damping=t.damping, cg_iters=t.cg_iters,
                    backtrack_ratio=t.backtrack_ratio, max_backtracks=t.max_backtracks)
    meta = {"env": cfg.env.name, "obs_dim": obs_dim, "act_dim": act_dim, "policy_hidden": list(cfg.policy.hidden),
            "policy_init_std": cfg.policy.init_std, "dynamics_hidden": list(dyn.hidden),
            "prior_std": dyn.prior_std, "likelihood_std": dyn.likelihood_std}
    counters = {"iteration": 0, "frames": 0}
    replay = holdout = first_batch = seen = None
    initial_coverage: dict[str, float] = {}
    # FileNotFoundError says what is missing; ValueError if the checkpoint's format or meta differ
    state = VIME_FORMAT.load_for_resume(checkpointer, meta) if cfg.resume else None
    if state is not None:
        policy.load_state_dict(state["policy"])
        dynamics.load_state_dict(state["dynamics"])
        optimizer.load_state_dict(state["dynamics_optimizer"])
        bonus.median_history.copy_(state["median_history"])
        replay, holdout, seen = state["replay"], state["holdout"], state["visited"]
        counters.update(state["counters"])
        initial_coverage = state["initial_coverage"]
        torch.set_rng_state(state["rng"])

    def save() -> Path:
        keep = cfg.checkpoint.save_replay
        return save_vime_checkpoint(
            checkpointer, meta=meta, policy=policy, dynamics=dynamics, dynamics_optimizer=optimizer,
            median_history=bonus.median_history, replay=replay if keep else None,
            holdout=holdout if keep else None, counters=counters, initial_coverage=initial_coverage, visited=seen,
            config=cfg)

    if counters["iteration"] >= cfg.iterations:
        raise ValueError(f"nothing to do: the checkpoint is at iteration {counters['iteration']} >= "
                         f"iterations={cfg.iterations}; raise iterations.")
    logger = make_logger(cfg.logger, exp_name=cfg.logger.exp_name, config=cfg, log_dir=out_dir)
    progress = tqdm.tqdm(total=cfg.iterations, initial=counters["iteration"], disable=not cfg.progress,
                         unit="it", desc=f"VIME {cfg.env.name}")
    start, metrics, batch = time.perf_counter(), {}, None
    while counters["iteration"] < cfg.iterations:
        tic = time.perf_counter()
        batch = collect(env, policy, num_tasks=1, horizon=cfg.env.horizon)[0]  # [N, H]
        collect_s = time.perf_counter() - tic
        coverage = state_coverage(batch, cfg.env.name, cfg.coverage.cell_size)
        seen, cumulative = cumulative_coverage(seen, batch, cfg.env.name, cfg.coverage.cell_size)
        if counters["iteration"] == 0:
            initial_coverage, first_batch = coverage, batch.clone()

        tic = time.perf_counter()
        bonus(batch)  # ("next", "reward") <- 0 + eta * info gain / median, from the model before it sees the batch
        bonus_s = time.perf_counter() - tic
        if cfg.bonus.shuffle:  # control run: same bonus values, no link to the transitions that earned them
            reward = batch["next", "reward"]
            reward[batch["mask"]] = reward[batch["mask"]][torch.randperm(int(batch["mask"].sum()))]
        valid = batch[batch["mask"]].select(*TRANSITION_KEYS)
        held = torch.rand(valid.shape[0]) < dyn.holdout_fraction
        replay = append(replay, valid[~held], dyn.replay_size)
        holdout = append(holdout, valid[held], dyn.holdout_size)

        tic = time.perf_counter()
        dynamics.update_normalizer(*(valid[k] for k in TRANSITION_KEYS))
        dyn_metrics = train_dynamics(loss_fn, optimizer, replay, cfg)
        if holdout.shape[0]:
            dyn_metrics.update(heldout_metrics(loss_fn, holdout))
        dynamics_s = time.perf_counter() - tic

        tic = time.perf_counter()
        compute_advantages(batch, gamma=t.gamma, lmbda=t.gae_lambda)
        trpo_info = trpo_update(trpo, policy, params, batch)
        policy_s = time.perf_counter() - tic

        counters["iteration"] += 1
        counters["frames"] += batch.numel()
        mask = batch["mask"]
        info_gain, intrinsic = batch["next", "info_gain"][mask], batch["next", "intrinsic_reward"][mask]
        metrics = {
            "bonus/info_gain_median": float(info_gain.median()), "bonus/info_gain_mean": float(info_gain.mean()),
            "bonus/info_gain_max": float(info_gain.max()), "bonus/intrinsic_mean": float(intrinsic.mean()),
            "bonus/intrinsic_max": float(intrinsic.max()),
            "bonus/intrinsic_return": float((batch["next", "reward"].squeeze(-1) * mask).sum(-1).mean()),
            **{f"dynamics/{k}": v for k, v in dyn_metrics.items()},
            **{f"trpo/{k}": v for k, v in trpo_info.items()},
            "policy/action_std": float(batch["scale"].mean()),
            **{f"coverage/{k}": v for k, v in {**coverage, **cumulative}.items()},
            **{f"coverage/initial_{k}": v for k, v in initial_coverage.items()},
            "time/env_steps_per_s": batch.numel() / max(collect_s, 1e-9), "time/collect_s": collect_s,
            "time/bonus_s": bonus_s, "time/dynamics_s": dynamics_s, "time/policy_s": policy_s,
            "time/elapsed_s": time.perf_counter() - start, "train/frames": counters["frames"],
        }
        if not all(math.isfinite(v) for v in metrics.values()):
            raise FloatingPointError(f"non-finite metrics at iteration {counters['iteration']}: "
                                     f"{ {k: v for k, v in metrics.items() if not math.isfinite(v)} }")
        log_metrics(logger, metrics, counters["iteration"])
        progress.update(1)
        progress.set_postfix({k.split("/")[-1]: f"{metrics[k]:.3g}" for k in
                              ("coverage/cells", "coverage/velocity_range", "dynamics/heldout_log_likelihood")
                              if k in metrics})
        if counters["iteration"] % cfg.checkpoint.every == 0:
            save()
    progress.close()
    if first_batch is not None and cfg.env.name != "half_cheetah":
        plot_coverage(first_batch, batch, cfg.env.name, out_dir / "figures" / "coverage.png")
    path = save()
    env.close()
    return {**metrics, "checkpoint": str(path)}


@hydra.main(version_base="1.3", config_path="config", config_name="vime")
def main(cfg: DictConfig) -> None:
    result = train(cfg)
    print({k: (round(v, 4) if isinstance(v, float) else v) for k, v in result.items()})


if __name__ == "__main__":
    main()
