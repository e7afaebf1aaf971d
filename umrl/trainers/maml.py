"""MAML meta-training on proposed tasks as a library object: :class:`MAMLTrainer` (UML-DIAYN, UML-random, oracle).

``proposal=random_arena`` is an ablation, not the paper's method: UML-random meta-trained with point_nav's position
clipped to [-a, a]² (``env.arena``, 1.0 when null); see :mod:`umrl.proposals`.

One meta-iteration (:func:`meta_iteration`): ``proposal.resample`` picks T tasks -> collect each task's pre-update
batch with θ (``sample_by=env_steps``: its first episodes up to N × H env steps,
:func:`umrl.rollout.collect_env_steps`; ``trajectories``: N trajectories, :func:`umrl.rollout.collect`) -> the loss's
value estimator (linear baseline + GAE) -> ``MAMLLoss.adapt`` (one PG step per task) -> collect the post-update batches the same way with every task's adapted parameters (one
batched policy call per env step) -> :class:`~umrl.optim.trpo.TRPOStep` on ``MAMLLoss``'s forward (the query
surrogate through the inner step), with the KL Hessian-vector product strategy ``trpo.hvp`` names
(:mod:`umrl.optim.meta_hvp`) on ``trpo.hvp_fraction`` of the trajectories.

Metrics of :meth:`MAMLTrainer.step`: ``train/`` return_pre, return_post (mean undiscounted return of the pre/post-update
trajectories), reward_mean/std/min/max (task rewards of the pre-update batch), kl, surrogate_before,
improvement, backtracks (line-search trials; of them rejected_surrogate and rejected_kl, of those nonfinite_kl),
accepted, grad_norm,
step_norm, log_std (θ's action log-std after the meta-step, mean over action dimensions); ``time/`` collect_s
(rollouts + advantages), learn_s (inner adaptation for the post-update policy + TRPO meta-step), inner_s (that
adaptation alone, built with the graph the meta-step differentiates through), the meta-step's parts objective_s
(surrogate and KL through the inner step), direction_s (gradient, HVP set-up, ``trpo.cg_iters`` products), cg_s
(those products alone) and line_search_s, env_steps_per_s (pre + post env steps per second of collect_s),
env_steps. Checkpoints: ``<output_dir>/checkpoints/step_<iteration>.pt`` (format in :mod:`umrl.checkpoints.maml`).

Example (tiny sizes; ``umrl.trainers.compose`` reads the defaults in ``umrl/configs/maml.yaml``):
    >>> from umrl.trainers import MAMLTrainer, compose
    >>> cfg = compose("maml", ["proposal=random", "iterations=2", "logger.backend=none"])  # doctest: +SKIP
    >>> trainer = MAMLTrainer(cfg)  # doctest: +SKIP
    >>> metrics = trainer.step()  # one meta-iteration  # doctest: +SKIP
    >>> result = trainer.train()  # the rest, logged and checkpointed  # doctest: +SKIP
"""
from __future__ import annotations

import contextlib
from collections.abc import Callable
from pathlib import Path

import torch
import tqdm
from omegaconf import DictConfig

from umrl.checkpoints import MAML_FORMAT, save_maml_checkpoint
from umrl.checkpoints.format import check_budget_left
from umrl.configs import check_resume, validate
from umrl.configs.maml import MAMLConfig
from umrl.folder_lock import claim_run_folder, releases_folder_on_error
from umrl.modules.policy import make_gaussian_policy, policy_log_std
from umrl.objectives.maml import MAMLLoss
from umrl.objectives.policy_gradient import episode_mean, episode_returns
from umrl.optim.meta_hvp import make_meta_hvp
from umrl.optim.trpo import TRPOStep
from umrl.profiling import device_clock
from umrl.proposals import make_proposal
from umrl.rollout import NonFiniteActions, check_cudagraphs, collect, collect_env_steps
from umrl.runtime import (
    Checkpointer,
    check_finite,
    close_logger,
    env_state,
    load_env_state,
    log_metrics,
    make_logger,
    rng_state,
    seed_everything,
    set_rng_state,
)
from umrl.signals import stop_requests
from umrl.validation import InvalidValue, resolve_device

__all__ = ["MAMLTrainer", "build", "meta_batch", "meta_iteration", "meta_step", "train"]


def meta_batch(cfg: DictConfig, proposal, policy, loss: MAMLLoss, generator: torch.Generator,
               *, learn_context: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext):
    """A fresh meta-batch: ``(support, adapted, query, inner_s)``.

    ``proposal.resample`` draws the tasks, ``support`` holds the pre-update trajectories with θ and their advantages,
    ``adapted`` every task's parameters after the inner step (built with the graph the meta-step differentiates
    through, under ``learn_context()``), ``query`` the post-update trajectories with them and their advantages;
    ``inner_s`` is the inner step's time."""
    num_tasks, horizon = proposal.num_tasks, cfg.env.horizon
    advantages = loss.value_estimator
    device = next(policy.parameters()).device
    proposal.resample(generator)
    sampling = {"num_tasks": num_tasks, "horizon": horizon, "cudagraphs": cfg.cudagraphs}
    if cfg.sample_by == "env_steps":
        sampler, sampling["env_steps"] = collect_env_steps, proposal.trajectories_per_task * horizon
    else:
        sampler = collect
    support = advantages(sampler(proposal.env, policy, **sampling))
    check_finite({"reward": support["next", "reward"]}, "the pre-update rollouts")
    inner_start = device_clock(device)
    with torch.enable_grad(), learn_context():  # the graph (second order unless first_order) is reused below
        adapted = loss.adapt(support)
    check_finite(dict(adapted.items(True, True)), "the adapted parameters (inner step)")
    inner_s = device_clock(device) - inner_start
    try:
        query = sampler(proposal.env, policy, params=adapted.detach(), **sampling)
    except NonFiniteActions as err:  # the inner step diverged
        raise InvalidValue("maml.inner_lr", cfg.maml.inner_lr, "a smaller finite number > 0",
                           note=f"the adapted policy's actions after the inner step: {err.note}") from err
    return support, adapted, advantages(query), inner_s


def meta_iteration(cfg: DictConfig, proposal, policy, loss: MAMLLoss, trpo: TRPOStep, generator: torch.Generator, *,
                   learn_context: Callable[[], contextlib.AbstractContextManager] = contextlib.nullcontext
                   ) -> dict[str, float]:
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
        info = meta_step(cfg, loss, trpo, support, query, adapted)
    learned = device_clock(device)

    reward = support["next", "reward"][support["mask"]]
    steps = support["mask"].numel() + query["mask"].numel()  # simulated, episodes past a budget's last one included
    collect_s, learn_s = collected - start - inner_s, learned - collected + inner_s
    phases = {k: info.pop(k) for k in ("direction_s", "cg_s", "line_search_s")}
    metrics = {f"train/{k}": v for k, v in info.items()}
    metrics.update({
        "train/return_pre": episode_mean(episode_returns(support), support).mean().item(),
        "train/return_post": episode_mean(episode_returns(query), query).mean().item(),
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


def meta_step(cfg: DictConfig, loss: MAMLLoss, trpo: TRPOStep, support, query, adapted) -> dict[str, float]:
    """TRPO's meta-step through the inner step (``adapted``: :func:`meta_batch`'s, with its graph), with the KL
    Hessian-vector product strategy ``trpo`` was built with (``cfg.trpo.hvp`` on ``cfg.trpo.hvp_fraction`` of the
    trajectories); updates the policy in place and returns :class:`~umrl.optim.trpo.TRPOStep`'s numbers."""
    with torch.enable_grad():  # the meta-step's first evaluation, through the inner step's graph
        first = loss(loss.pack(support, query, adapted))
    batch = loss.pack(support, query)

    def closure():
        out = loss(batch)
        return out["loss_objective"], out["trust_region_kl"]

    return trpo(closure, batch=batch, initial=(first["loss_objective"], first["trust_region_kl"]))


def build(cfg: DictConfig, generator: torch.Generator | None = None):
    """``(proposal, policy, loss, trpo)`` from the config (``benchmarks/meta_iteration.py`` times these too); the
    policy, the loss, TRPO's state and the proposal's env and discriminator live on ``cfg.device``. ``generator``
    draws the Hessian-vector products' trajectory share (``cfg.trpo.hvp_fraction``)."""
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
    # the same draw as every method's random init for this seed (scratch's, VIME's), whatever the proposal drew
    policy = make_gaussian_policy(obs_dim, act_dim, hidden=list(cfg.policy.hidden), init_std=cfg.policy.init_std,
                                  seed=cfg.seed)
    policy = policy.to(device)  # initialised on the CPU: the same weights on every device
    loss = MAMLLoss(policy, inner_lr=cfg.maml.inner_lr, num_inner_steps=cfg.maml.num_inner_steps,
                    first_order=cfg.maml.first_order, task_loop=cfg.maml.task_loop)
    loss.make_value_estimator(gamma=cfg.advantage.gamma, lmbda=cfg.advantage.lmbda, normalize=cfg.advantage.normalize)
    hvp = make_meta_hvp(cfg.trpo.hvp, loss, fraction=cfg.trpo.hvp_fraction, generator=generator)
    trpo = TRPOStep(loss.params, hvp=hvp, max_kl=cfg.trpo.max_kl, damping=cfg.trpo.damping, cg_iters=cfg.trpo.cg_iters,
                    backtrack_ratio=cfg.trpo.backtrack_ratio, max_backtracks=cfg.trpo.max_backtracks)
    return proposal, policy, loss, trpo


class MAMLTrainer:
    """MAML meta-training built from a config (checked against :class:`~umrl.configs.maml.MAMLConfig` first).

    Construction seeds every RNG (``cfg.seed``), builds the proposal, policy, loss and TRPO step (:func:`build`) and
    the checkpointer (``<output_dir>/checkpoints``); with ``cfg.resume`` it restores the latest checkpoint
    (:meth:`load_state_dict`), else it writes iteration 0 (the initialisation, the meta-training ablation's first
    point). A config that differs from the checkpoint's beyond ``umrl.configs.RESUME_ALLOW`` is refused.

    :meth:`step` runs one meta-iteration and returns its metrics; :meth:`train` steps to ``cfg.iterations``,
    logging (``cfg.logger``) and checkpointing (``cfg.checkpoint.every`` and the last); :meth:`state_dict` holds
    everything a resumed run needs to finish bit-identical to an uninterrupted one: the policy, the counters, every
    RNG (torch, numpy, python, the task generator) and the env's reset noise.

    Attributes: ``cfg`` (validated), ``proposal``, ``policy``, ``loss``, ``trpo``, ``generator`` (task draws and the
    HVP subsample), ``iteration``, ``env_steps``, ``checkpointer``.

    Construction first locks ``output_dir`` until :meth:`close` (:func:`umrl.folder_lock.claim_run_folder`: a folder
    another run uses, or one holding checkpoints while ``cfg.resume`` is false, is refused before any work).

    Nothing process-wide is set: the caller's torch thread count is used (``cfg.num_threads`` is applied by the
    command line, ``recipes/maml.py``, and by the suite's workers; :mod:`umrl.process`).
    """

    @releases_folder_on_error
    def __init__(self, cfg: DictConfig):
        self.cfg = cfg = validate(cfg, MAMLConfig)
        self.generator = seed_everything(cfg.seed)
        self.output_dir = Path(cfg.output_dir)
        self.checkpointer = Checkpointer(self.output_dir / "checkpoints", keep_all=cfg.checkpoint.keep_all)
        self.folder_lock = claim_run_folder(self.output_dir, resume=cfg.resume, checkpointers=[self.checkpointer])
        self.proposal, self.policy, self.loss, self.trpo = build(cfg, self.generator)
        env = self.proposal.env
        self.meta = {
            "env": cfg.env.name, "proposal": cfg.proposal, "obs_dim": env.observation_spec["observation"].shape[-1],
            "act_dim": env.action_spec.shape[-1], "hidden": list(cfg.policy.hidden), "init_std": cfg.policy.init_std,
            "inner_lr": cfg.maml.inner_lr, "num_inner_steps": cfg.maml.num_inner_steps,
            "first_order": cfg.maml.first_order, "num_tasks": self.proposal.num_tasks,
            "trajectories_per_task": self.proposal.trajectories_per_task, "horizon": cfg.env.horizon,
            "num_skills": self.proposal.num_skills,
        }
        self.iteration, self.env_steps = 0, 0
        # FileNotFoundError says what is missing; ConfigError lists changed keys; ValueError if format or meta differ
        state = (MAML_FORMAT.load_for_resume(self.checkpointer, self.meta, lambda saved: check_resume(saved, cfg))
                 if cfg.resume else None)
        if state is not None:
            self.load_state_dict(state)
            check_budget_left("iterations", cfg.iterations, self.iteration, "iterations", self.output_dir)
        else:
            self.save()
        self.logger = make_logger(cfg.logger, exp_name=cfg.logger.exp_name, job_type="maml", config=cfg,
                                  log_dir=self.output_dir)

    @property
    def done(self) -> bool:
        """Whether the budget (``cfg.iterations``) is reached."""
        return self.iteration >= self.cfg.iterations

    def step(self) -> dict[str, float]:
        """One meta-iteration (:func:`meta_iteration`): the policy is updated in place; returns its metrics."""
        metrics = meta_iteration(self.cfg, self.proposal, self.policy, self.loss, self.trpo, self.generator)
        self.iteration += 1
        self.env_steps += int(metrics["time/env_steps"])
        return metrics

    def state_dict(self) -> dict:
        """The policy's weights, ``iteration``, ``env_steps``, every RNG's state and the env's."""
        return {"policy": self.policy.state_dict(), "iteration": self.iteration, "env_steps": self.env_steps,
                "rng": rng_state(task=self.generator), "env": env_state(self.proposal.env)}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`'s (or a checkpoint's) policy, counters, RNGs and env."""
        self.policy.load_state_dict(state["policy"])
        self.iteration, self.env_steps = state["iteration"], state["env_steps"]
        set_rng_state(state["rng"], task=self.generator)
        load_env_state(self.proposal.env, state["env"])

    def save(self) -> Path:
        """Write the checkpoint of the current iteration; returns its path."""
        state = self.state_dict()
        return save_maml_checkpoint(self.checkpointer, meta=self.meta, policy=self.policy, iteration=self.iteration,
                                    env_steps=self.env_steps, rng=state["rng"], env=state["env"], config=self.cfg)

    def log(self, metrics: dict[str, float]) -> None:
        """Send ``metrics`` to the configured logger at the current iteration."""
        log_metrics(self.logger, metrics, self.iteration)

    def train(self) -> dict:
        """Step to ``cfg.iterations``, logging every iteration and checkpointing every ``cfg.checkpoint.every`` and
        at the last; returns the last iteration's metrics, ``iteration`` and the last ``checkpoint`` path (a run
        resumed at its budget is refused at construction). A SIGTERM or SIGINT finishes the meta-iteration in
        progress, saves it and raises :class:`~umrl.signals.TrainingStopped` (:mod:`umrl.signals`)."""
        cfg, metrics = self.cfg, {}
        path, saved = self.checkpointer.latest(), self.iteration
        progress = tqdm.tqdm(total=cfg.iterations, initial=self.iteration, disable=not cfg.progress,
                             desc="meta-iterations")
        with stop_requests() as stop:
            while not self.done and not stop:
                metrics = self.step()
                self.log(metrics)
                progress.update(1)
                progress.set_postfix(pre=f"{metrics['train/return_pre']:.1f}",
                                     post=f"{metrics['train/return_post']:.1f}", kl=f"{metrics['train/kl']:.4f}",
                                     learn=f"{metrics['time/learn_s']:.1f}s")
                if self.iteration % cfg.checkpoint.every == 0 or self.done:  # and always the last one
                    path, saved = self.save(), self.iteration
            progress.close()
            if stop and not self.done:
                path = path if path is not None and saved == self.iteration else self.save()
                raise stop.stopped(f"after meta-iteration {self.iteration} of {cfg.iterations}", path)
        return {**metrics, "iteration": self.iteration, "checkpoint": str(path)}

    def close(self) -> None:
        """Close the env (and its worker threads), finish the logger's run and release ``output_dir``."""
        self.proposal.env.close()
        close_logger(self.logger)
        self.folder_lock.release()


def train(cfg: DictConfig) -> dict:
    """Meta-train as configured in this process (:class:`MAMLTrainer`, then closed): the last iteration's metrics,
    ``iteration`` and the final ``checkpoint`` path."""
    trainer = MAMLTrainer(cfg)
    try:
        return trainer.train()
    finally:
        trainer.close()
