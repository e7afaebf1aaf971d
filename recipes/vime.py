"""VIME pre-training: TRPO on the information-gain bonus alone (the VIME-init baseline's policy).

    python recipes/vime.py env.name=point_nav                     # 30 iterations of 40 x 100 steps
    python recipes/vime.py env.name=half_cheetah logger.backend=csv
    python recipes/vime.py env.name=point_nav resume=true         # continue from the latest checkpoint

Each iteration: collect ``env.num_envs`` trajectories of ``env.horizon`` steps with the current policy
(:func:`umrl.rollout.collect`, one batched policy call per step) -> score every transition with
:class:`~umrl.transforms.vime_bonus.VIMEBonus` using the dynamics model *before* it sees them (the reward is the bonus
alone: the CMP's reward is zero) -> add them to the dynamics model's FIFO replay (a TorchRL ``ReplayBuffer`` over a
``LazyTensorStorage``; a share goes to a held-out one) ->
update the running input/target statistics and train the model (:class:`~umrl.objectives.vime.VIMELoss`, Adam) ->
one TRPO step (:class:`umrl.optim.trpo.TRPOStep`) on the importance-ratio surrogate (``MAMLLoss``'s outer
objective with no inner step) with linear-baseline GAE advantages
(:func:`umrl.objectives.policy_gradient.compute_advantages`).

Logged (namespaced): ``bonus/`` info gain and bonus statistics; ``dynamics/`` training loss, log-likelihood, KL to
the prior, held-out log-likelihood and ELBO per transition; ``train/`` the TRPO step's improvement, KL, acceptance,
backtracks (the names MAML's meta-step logs), action_std and frames;
``coverage/`` of the batch's visited states (x-y cells and their area for point_nav and ant, velocity ranges for
half_cheetah), the untrained policy's under ``coverage/initial_*`` and everything visited so far under
``coverage/cumulative_*`` (all from :mod:`umrl.skill_coverage`); ``time/`` env steps/s and seconds per phase (the
TRPO step's direction_s, cg_s and line_search_s too, as in MAML's). The
figure ``<output_dir>/figures/coverage.png`` shows the last batch's visited states against the untrained policy's.

Checkpoints: ``<output_dir>/checkpoints/step_<iteration>.pt``, format ``umrl.vime.v1`` (documented in
:mod:`umrl.checkpoints.vime`); ``umrl.checkpoints.load_vime_policy(path)`` returns the policy to fine-tune.
``resume=true`` restores the policy, the dynamics model and its optimiser, the bonus normaliser, the transitions,
the counters, every RNG and the env's reset noise (bit-identical to an uninterrupted run).
"""
from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import hydra
import torch
import tqdm
from omegaconf import DictConfig
from tensordict import TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBuffer, TensorDictReplayBuffer

from recipes import register_help_text
from umrl.checkpoints import VIME_FORMAT, save_vime_checkpoint
from umrl.configs import check_resume, validate
from umrl.configs.vime import VIMEConfig
from umrl.envs import get_env_spec, make_env
from umrl.heap import keep_freed_memory
from umrl.modules.bnn import BayesianDynamics
from umrl.modules.policy import make_gaussian_policy
from umrl.objectives.maml import MAMLLoss
from umrl.objectives.policy_gradient import compute_advantages
from umrl.objectives.vime import VIMELoss
from umrl.optim.trpo import TRPOStep
from umrl.rollout import collect
from umrl.runtime import (
    Checkpointer,
    check_finite,
    env_state,
    finishing_loggers,
    load_env_state,
    load_replay_buffer_state,
    log_location,
    log_metrics,
    make_logger,
    replay_buffer_state,
    rng_state,
    run_summary,
    seed_everything,
    set_rng_state,
)
from umrl.skill_coverage import cumulative_coverage, plot_coverage, state_coverage, visited_states
from umrl.transforms.vime_bonus import VIMEBonus
from umrl.validation import resolve_device

TRANSITION_KEYS = ("observation", "action", ("next", "observation"))


def trpo_update(trpo: TRPOStep, loss: MAMLLoss, batch: TensorDictBase) -> dict[str, float]:
    """One TRPO step on the importance-ratio surrogate ``-mean(ratio * advantage)`` with the mean KL(old || new)
    over the valid steps: ``MAMLLoss``'s outer objective with no inner step (``batch`` is one task's ``[N, H]``)."""
    task = batch.unsqueeze(0)  # [1, N, H]: the support and the query of a single task
    return trpo(lambda: loss.objective_and_kl(task, task))


def train_dynamics(loss_fn: VIMELoss, optimizer, replay: ReplayBuffer, cfg: DictConfig) -> dict[str, float]:
    """``updates_per_iteration`` Adam steps on random minibatches of the replay; mean diagnostics."""
    loss_fn.dataset_size = len(replay)
    logs = []
    for _ in range(cfg.dynamics.updates_per_iteration):
        out = loss_fn(replay.sample(cfg.dynamics.batch_size))
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


@finishing_loggers()
def train(cfg: DictConfig) -> dict:
    """Run VIME pre-training as configured (checked against :class:`~umrl.configs.vime.VIMEConfig` first); return
    the last metrics and the checkpoint path. ``resume=true`` (with ``checkpoint.save_replay=true``, the default)
    finishes bit-identical to an uninterrupted run; a config that differs from the checkpoint's beyond
    ``umrl.configs.RESUME_ALLOW`` is refused."""
    cfg = validate(cfg, VIMEConfig)
    torch.set_num_threads(cfg.num_threads)
    keep_freed_memory()
    seed_everything(cfg.seed)
    device = torch.device(resolve_device("device", cfg.device))  # networks, replay storage, env outputs
    out_dir = Path(cfg.output_dir)
    checkpointer = Checkpointer(out_dir / "checkpoints", keep_all=cfg.checkpoint.keep_all)

    env = make_env(cfg.env.name, cfg.env.num_envs, seed=cfg.seed, device=device, horizon=cfg.env.horizon,
                   backend=cfg.env.backend)
    obs_dim, act_dim = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    # initialised on the CPU (the same weights on every device), then moved
    policy = make_gaussian_policy(obs_dim, act_dim, hidden=list(cfg.policy.hidden),
                                  init_std=cfg.policy.init_std).to(device)
    dyn = cfg.dynamics
    dynamics = BayesianDynamics(obs_dim, act_dim, hidden=list(dyn.hidden), prior_std=dyn.prior_std,
                                likelihood_std=dyn.likelihood_std, init_std=dyn.init_std).to(device)
    loss_fn = VIMELoss(dynamics, dataset_size=1, num_samples=dyn.num_samples)
    optimizer = torch.optim.Adam(dynamics.parameters(), lr=dyn.lr)
    bonus = VIMEBonus(dynamics, eta=cfg.bonus.eta, num_samples=cfg.bonus.num_samples,
                      median_window=cfg.bonus.median_window).to(device)
    surrogate = MAMLLoss(policy, num_inner_steps=0)  # TRPO's surrogate: MAML's outer objective, no inner step
    t = cfg.trpo
    trpo = TRPOStep(surrogate.params, max_kl=t.max_kl, damping=t.damping, cg_iters=t.cg_iters,
                    backtrack_ratio=t.backtrack_ratio, max_backtracks=t.max_backtracks)
    meta = {"env": cfg.env.name, "obs_dim": obs_dim, "act_dim": act_dim, "policy_hidden": list(cfg.policy.hidden),
            "policy_init_std": cfg.policy.init_std, "dynamics_hidden": list(dyn.hidden),
            "prior_std": dyn.prior_std, "likelihood_std": dyn.likelihood_std}
    counters = {"iteration": 0, "frames": 0}
    replay = TensorDictReplayBuffer(storage=LazyTensorStorage(dyn.replay_size, device=device),
                                    batch_size=dyn.batch_size)
    holdout = TensorDictReplayBuffer(storage=LazyTensorStorage(dyn.holdout_size, device=device))
    initial_states = seen = None  # the untrained policy's visited states: the coverage figure's baseline
    initial_coverage: dict[str, float] = {}
    # FileNotFoundError says what is missing; ConfigError lists changed keys; ValueError if format or meta differ
    state = VIME_FORMAT.load_for_resume(checkpointer, meta, lambda saved: check_resume(saved, cfg)) if cfg.resume else None
    if state is not None:
        policy.load_state_dict(state["policy"])
        dynamics.load_state_dict(state["dynamics"])
        optimizer.load_state_dict(state["dynamics_optimizer"])
        bonus.median_history.copy_(state["median_history"])
        for buffer, stored in ((replay, state["replay"]), (holdout, state["holdout"])):
            if stored is not None:  # TorchRL's buffer state: contents, write cursor, sampler
                load_replay_buffer_state(buffer, stored)
        seen = None if state["visited"] is None else state["visited"].to(device)
        counters.update(state["counters"])
        initial_coverage, initial_states = state["initial_coverage"], state["initial_states"]
        set_rng_state(state["rng"])
        load_env_state(env, state["env"])

    def save() -> Path:
        keep = cfg.checkpoint.save_replay
        return save_vime_checkpoint(
            checkpointer, meta=meta, policy=policy, dynamics=dynamics, dynamics_optimizer=optimizer,
            median_history=bonus.median_history, replay=replay_buffer_state(replay) if keep else None,
            holdout=replay_buffer_state(holdout) if keep else None, counters=counters, initial_coverage=initial_coverage,
            initial_states=initial_states, visited=seen, rng=rng_state(), env=env_state(env), config=cfg)

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
            initial_coverage, initial_states = coverage, visited_states(batch, cfg.env.name).cpu()

        tic = time.perf_counter()
        bonus(batch)  # ("next", "reward") <- 0 + eta * info gain / median, from the model before it sees the batch
        bonus_s = time.perf_counter() - tic
        if cfg.bonus.shuffle:  # control run: same bonus values, no link to the transitions that earned them
            reward = batch["next", "reward"]
            reward[batch["mask"]] = reward[batch["mask"]][torch.randperm(int(batch["mask"].sum()))]
        valid = batch[batch["mask"]].select(*TRANSITION_KEYS)
        held = (torch.rand(valid.shape[0]) < dyn.holdout_fraction).to(valid.device)  # CPU draw: same split anywhere
        for buffer, part in ((replay, valid[~held]), (holdout, valid[held])):
            if part.shape[0]:
                buffer.extend(part)

        tic = time.perf_counter()
        dynamics.update_normalizer(*(valid[k] for k in TRANSITION_KEYS))
        dyn_metrics = train_dynamics(loss_fn, optimizer, replay, cfg)
        if len(holdout):
            dyn_metrics.update(heldout_metrics(loss_fn, holdout[:]))
        dynamics_s = time.perf_counter() - tic

        tic = time.perf_counter()
        compute_advantages(batch, gamma=t.gamma, lmbda=t.gae_lambda)
        trpo_info = trpo_update(trpo, surrogate, batch)
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
            **{f"{'time' if k.endswith('_s') else 'train'}/{k}": v for k, v in trpo_info.items()},
            "train/action_std": float(batch["scale"].mean()),
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
        if counters["iteration"] % cfg.checkpoint.every == 0 or counters["iteration"] == cfg.iterations:
            path = save()  # and always the last iteration (the figure below draws no random numbers)
    progress.close()
    if initial_states is not None:  # also on a resumed run
        spec = get_env_spec(cfg.env.name)
        plot_coverage(visited_states(batch, cfg.env.name), out_dir / "figures" / "coverage.png",
                      eval_tasks=spec.eval_tasks(),
                      baseline=initial_states, label="VIME policy",
                      baseline_label="initial policy", title=f"VIME {cfg.env.name}: visited states")
    env.close()
    return {**metrics, "checkpoint": str(path)}


SUMMARY_KEYS = ("train/frames", "bonus/info_gain_median", "dynamics/heldout_log_likelihood", "coverage/cumulative_area",
                "coverage/cumulative_velocity_range")
"""What the command line prints when a run ends (every metric is in the logs)."""


@hydra.main(version_base="1.3", config_path="config", config_name="vime")
def main(cfg: DictConfig) -> None:
    result = train(cfg)
    logging.getLogger(__name__).info(run_summary(f"vime {cfg.env.name} finished", result, SUMMARY_KEYS,
                                                 log_location(cfg.logger, cfg.output_dir)))


if __name__ == "__main__":
    register_help_text()
    main()
