"""MAML meta-training on proposed tasks: UML-DIAYN, UML-random, or the oracle task family.

``proposal=random_arena`` is an ablation, not the paper's method: UML-random meta-trained with point_nav's position
clipped to [-a, a]² (``env.arena``, 1.0 when null); see :mod:`umrl.proposals`.

    python recipes/maml.py proposal=oracle                                   # hand-designed goals (upper bound)
    python recipes/maml.py proposal=random                                   # frozen random discriminator
    python recipes/maml.py proposal=diayn diayn_checkpoint=outputs/diayn/point_nav/seed0
    python recipes/maml.py proposal=oracle resume=true                       # continue from the latest checkpoint

One meta-iteration: ``proposal.resample`` picks T tasks -> :func:`umrl.rollout.collect` N pre-update trajectories
per task with θ -> :func:`~umrl.objectives.policy_gradient.compute_advantages` -> ``MAMLLoss.adapt`` (one PG step
per task) -> collect N post-update trajectories per task with every task's adapted parameters (one vmapped policy
call per env step) -> :class:`~umrl.optim.trpo.TRPOStep` on the query surrogate, with KL Hessian-vector products
taken through the inner step (optionally on ``trpo.hvp_fraction`` of the trajectories): ``trpo.hvp=gauss_newton``
(default, ``MAMLLoss.gauss_newton_hvp``: exact at the current point, no third-order derivatives), ``analytic``
(``MAMLLoss.analytic_gauss_newton_hvp``: the same product derived by hand, equal to float rounding and faster on a
CPU) or ``exact`` (double backward of the KL through the inner step).

Logged per iteration: ``train/`` return_pre, return_post (mean undiscounted return of the pre/post-update
trajectories), reward_mean/std/min/max (task rewards of the pre-update batch), kl, surrogate_before,
improvement, backtracks (line-search trials; of them rejected_surrogate and rejected_kl, of those nonfinite_kl), accepted, grad_norm,
step_norm, log_std (θ's action log-std after the meta-step, mean over action dimensions); ``time/`` collect_s
(rollouts + advantages), learn_s (inner adaptation for the post-update policy + TRPO meta-step), inner_s (that
adaptation alone, built with the graph the meta-step differentiates through), the meta-step's parts objective_s (surrogate and KL through
the inner step), direction_s (gradient, HVP set-up, ``trpo.cg_iters`` products), cg_s (those products alone) and
line_search_s, env_steps_per_s (pre + post env steps per second of collect_s), env_steps. Checkpoints: ``<output_dir>/checkpoints/step_<iteration>.pt`` (format in :mod:`umrl.checkpoints.maml`).
"""
from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable
from pathlib import Path

import hydra
import torch
import tqdm
from omegaconf import DictConfig

from recipes import register_help_text
from umrl.checkpoints import MAML_FORMAT, save_maml_checkpoint
from umrl.configs import check_resume, validate
from umrl.configs.maml import MAMLConfig
from umrl.heap import keep_freed_memory
from umrl.modules.policy import make_gaussian_policy, policy_log_std
from umrl.objectives.maml import MAMLLoss
from umrl.objectives.policy_gradient import compute_advantages, episode_returns
from umrl.optim.trpo import TRPOStep
from umrl.profiling import device_clock
from umrl.proposals import make_proposal
from umrl.rollout import check_cudagraphs, collect
from umrl.runtime import (
    Checkpointer,
    check_finite,
    env_state,
    finishing_loggers,
    load_env_state,
    log_location,
    log_metrics,
    make_logger,
    rng_state,
    run_summary,
    seed_everything,
    set_rng_state,
)
from umrl.validation import resolve_device


def meta_batch(cfg: DictConfig, proposal, policy, loss: MAMLLoss, generator: torch.Generator,
               *, learn_context: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext):
    """A fresh meta-batch: ``(support, adapted, query, inner_s)``.

    ``proposal.resample`` draws the tasks, ``support`` holds the pre-update trajectories with θ and their advantages,
    ``adapted`` every task's parameters after the inner step (built with the graph the meta-step differentiates
    through, under ``learn_context()``), ``query`` the post-update trajectories with them and their advantages;
    ``inner_s`` is the inner step's time."""
    num_tasks, horizon = proposal.num_tasks, cfg.env.horizon
    adv = {"gamma": cfg.advantage.gamma, "lmbda": cfg.advantage.lmbda, "normalize": cfg.advantage.normalize}
    device = next(policy.parameters()).device
    proposal.resample(generator)
    graphs = {"cudagraphs": cfg.cudagraphs}
    support = compute_advantages(collect(proposal.env, policy, num_tasks=num_tasks, horizon=horizon, **graphs), **adv)
    check_finite({"reward": support["next", "reward"]}, "the pre-update rollouts")
    inner_start = device_clock(device)
    with torch.enable_grad(), learn_context():  # the graph (second order unless first_order) is reused below
        adapted = loss.adapt(support)
    check_finite(dict(adapted.items(True, True)), "the adapted parameters (inner step)")
    inner_s = device_clock(device) - inner_start
    query = collect(proposal.env, policy, num_tasks=num_tasks, horizon=horizon, params=adapted.detach(), **graphs)
    return support, adapted, compute_advantages(query, **adv), inner_s


def meta_iteration(cfg: DictConfig, proposal, policy, loss: MAMLLoss, trpo: TRPOStep, generator: torch.Generator,
                   *, learn_context: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext) -> dict[str, float]:
    """Collect support and query batches for a fresh meta-batch (:func:`meta_batch`) and take one TRPO meta-step
    (:func:`meta_step`); return metrics.

    ``learn_context`` makes the context manager that wraps each part of the learning step alone: it is called twice
    per iteration, for the inner adaptation and for the TRPO step (the query collection runs between them), e.g.
    fresh FLOP counters (``benchmarks/meta_iteration.py``; one ``FlopCounterMode`` entered twice would forget the
    first part). Times are taken after the device's queued work (CUDA) has finished."""
    device = next(policy.parameters()).device
    start = device_clock(device)
    support, adapted, query, inner_s = meta_batch(cfg, proposal, policy, loss, generator, learn_context=learn_context)
    collected = device_clock(device)
    with learn_context():
        info = meta_step(cfg, loss, trpo, support, query, adapted, generator)
    learned = device_clock(device)

    reward = support["next", "reward"][support["mask"]]
    steps = 2 * support["mask"].numel()
    collect_s, learn_s = collected - start - inner_s, learned - collected + inner_s
    phases = {k: info.pop(k) for k in ("direction_s", "cg_s", "line_search_s")}
    metrics = {f"train/{k}": v for k, v in info.items()}
    metrics.update({
        "train/return_pre": episode_returns(support).mean().item(),
        "train/return_post": episode_returns(query).mean().item(),
        "train/reward_mean": reward.mean().item(),
        "train/reward_std": reward.std().item(),
        "train/reward_min": reward.min().item(),
        "train/reward_max": reward.max().item(),
        "train/log_std": policy_log_std(policy).mean().item(),
        "time/collect_s": collect_s,
        "time/learn_s": learn_s,
        "time/inner_s": inner_s,
        # the meta-step's parts: the surrogate and KL through the inner step (what TRPO's two phases leave), the
        # search direction (gradient, HVP set-up, conjugate gradient), the line search
        "time/objective_s": learned - collected - phases["direction_s"] - phases["line_search_s"],
        **{f"time/{k}": v for k, v in phases.items()},
        "time/env_steps_per_s": steps / collect_s,
        "time/env_steps": float(steps),
    })
    return metrics


def meta_step(cfg: DictConfig, loss: MAMLLoss, trpo: TRPOStep, support, query, adapted,
              generator: torch.Generator) -> dict[str, float]:
    """TRPO's meta-step through the inner step (``adapted``: :func:`meta_batch`'s, with its graph), with the KL
    Hessian-vector products ``cfg.trpo.hvp`` names on ``cfg.trpo.hvp_fraction`` of the trajectories (drawn by
    ``generator``); updates the policy in place and returns :class:`~umrl.optim.trpo.TRPOStep`'s numbers."""
    fraction = cfg.trpo.hvp_fraction
    with torch.enable_grad():  # the meta-step's first evaluation, through the inner step's graph
        initial = loss.objective_and_kl(support, query, phi=adapted)

    def closure():
        return loss.objective_and_kl(support, query)

    if cfg.trpo.hvp in ("gauss_newton", "analytic"):
        product = loss.gauss_newton_hvp if cfg.trpo.hvp == "gauss_newton" else loss.analytic_gauss_newton_hvp
        return trpo(closure, initial=initial,
                    hvp=lambda: product(support, query, fraction=fraction, generator=generator))
    if fraction < 1:
        return trpo(closure, lambda: loss.hvp_kl(support, query, fraction=fraction, generator=generator),
                    initial=initial)
    return trpo(closure, initial=initial)  # the closure's own KL graph


def build(cfg: DictConfig):
    """``(proposal, policy, loss, trpo)`` from the config (``benchmarks/meta_iteration.py`` times these too); the
    policy, the loss, TRPO's state and the proposal's env and discriminator live on ``cfg.device``."""
    device = torch.device(resolve_device("device", cfg.device))
    proposal = make_proposal(
        cfg.proposal, cfg.env.name, num_tasks=cfg.meta_batch_size, trajectories_per_task=cfg.trajectories_per_task,
        seed=cfg.seed, horizon=cfg.env.horizon, num_skills=cfg.num_skills,
        diayn_checkpoint=cfg.diayn_checkpoint if cfg.proposal == "diayn" else None, device=device,
        arena=cfg.env.arena,
    )
    env = proposal.env
    if cfg.cudagraphs:
        check_cudagraphs(env)
    obs_dim, act_dim = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    policy = make_gaussian_policy(obs_dim, act_dim, hidden=list(cfg.policy.hidden), init_std=cfg.policy.init_std)
    policy = policy.to(device)  # initialised on the CPU: the same weights on every device
    loss = MAMLLoss(policy, inner_lr=cfg.maml.inner_lr, num_inner_steps=cfg.maml.num_inner_steps,
                    first_order=cfg.maml.first_order, task_loop=cfg.maml.task_loop)
    trpo = TRPOStep(loss.params, max_kl=cfg.trpo.max_kl, damping=cfg.trpo.damping, cg_iters=cfg.trpo.cg_iters,
                    backtrack_ratio=cfg.trpo.backtrack_ratio, max_backtracks=cfg.trpo.max_backtracks)
    return proposal, policy, loss, trpo


@finishing_loggers()
def train(cfg: DictConfig) -> dict:
    """Meta-train as configured (checked against :class:`~umrl.configs.maml.MAMLConfig` first); return the last
    iteration's metrics and the final checkpoint path. ``resume=true`` restores the policy, the counters, every RNG
    (torch, numpy, python, the task generator) and the env's reset noise: the run finishes bit-identical to an
    uninterrupted one; a config that differs from the checkpoint's beyond ``umrl.configs.RESUME_ALLOW`` is refused."""
    cfg = validate(cfg, MAMLConfig)
    torch.set_num_threads(cfg.num_threads)
    keep_freed_memory()
    generator = seed_everything(cfg.seed)
    out_dir = Path(cfg.output_dir)
    checkpointer = Checkpointer(out_dir / "checkpoints", keep_all=cfg.checkpoint.keep_all)
    proposal, policy, loss, trpo = build(cfg)
    env = proposal.env
    obs_dim, act_dim = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    meta = {
        "env": cfg.env.name, "proposal": cfg.proposal, "obs_dim": obs_dim, "act_dim": act_dim,
        "hidden": list(cfg.policy.hidden), "init_std": cfg.policy.init_std, "inner_lr": cfg.maml.inner_lr,
        "num_inner_steps": cfg.maml.num_inner_steps, "first_order": cfg.maml.first_order,
        "num_tasks": proposal.num_tasks, "trajectories_per_task": proposal.trajectories_per_task,
        "horizon": cfg.env.horizon, "num_skills": proposal.num_skills,
    }
    iteration, env_steps = 0, 0
    # FileNotFoundError says what is missing; ConfigError lists changed keys; ValueError if format or meta differ
    state = MAML_FORMAT.load_for_resume(checkpointer, meta, lambda saved: check_resume(saved, cfg)) if cfg.resume else None
    if state is not None:
        policy.load_state_dict(state["policy"])
        iteration, env_steps = state["iteration"], state["env_steps"]
        set_rng_state(state["rng"], task=generator)
        load_env_state(env, state["env"])
        if iteration >= cfg.iterations:  # as DIAYN and VIME: a resume with nothing to do is a mistake
            raise ValueError(f"nothing to do: the checkpoint is at iteration {iteration} >= iterations={cfg.iterations}; "
                             "raise iterations.")

    def save():
        return save_maml_checkpoint(checkpointer, meta=meta, policy=policy, iteration=iteration,
                                    env_steps=env_steps, rng=rng_state(task=generator), env=env_state(env), config=cfg)

    if state is None:
        save()  # iteration 0: the initialisation before meta-training, the ablation's first point
    logger = make_logger(cfg.logger, exp_name=cfg.logger.exp_name, config=cfg, log_dir=out_dir)
    metrics: dict[str, float] = {}
    path = checkpointer.latest()
    progress = tqdm.tqdm(total=cfg.iterations, initial=iteration, disable=not cfg.progress, desc="meta-iterations")
    while iteration < cfg.iterations:
        metrics = meta_iteration(cfg, proposal, policy, loss, trpo, generator)
        iteration += 1
        env_steps += int(metrics["time/env_steps"])
        log_metrics(logger, metrics, iteration)
        progress.update(1)
        progress.set_postfix(pre=f"{metrics['train/return_pre']:.1f}", post=f"{metrics['train/return_post']:.1f}",
                             kl=f"{metrics['train/kl']:.4f}", learn=f"{metrics['time/learn_s']:.1f}s")
        if iteration % cfg.checkpoint.every == 0 or iteration == cfg.iterations:  # and always the last one
            path = save()
    progress.close()
    env.close()
    return {**metrics, "iteration": iteration, "checkpoint": str(path)}


SUMMARY_KEYS = ("iteration", "train/return_pre", "train/return_post", "train/kl", "time/learn_s")
"""What the command line prints when a run ends (every metric is in the logs)."""


@hydra.main(version_base="1.3", config_path="config", config_name="maml")
def main(cfg: DictConfig) -> None:
    result = train(cfg)
    logging.getLogger(__name__).info(run_summary(f"maml {cfg.env.name} finished", result, SUMMARY_KEYS,
                                                 log_location(cfg.logger, cfg.output_dir)))


if __name__ == "__main__":
    register_help_text()
    main()
