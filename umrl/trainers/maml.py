"""MAML meta-training on proposed tasks as a library object: :class:`MAMLTrainer` (UML-DIAYN, UML-random, oracle).

``proposal=random_arena`` is an ablation, not the paper's method: UML-random meta-trained with point_nav's position
clipped to [-a, a]² (``env.arena``, 1.0 when null); see :mod:`umrl.proposals`.

One meta-iteration (:meth:`MAMLTrainer.step`): ``proposal.resample`` picks T tasks -> collect each task's
pre-update batch with θ (``sample_by=env_steps``: its first episodes up to N × H env steps,
:func:`umrl.rollout.collect_env_steps`; ``trajectories``: N trajectories, :func:`umrl.rollout.collect`) -> the
loss's value estimator (linear baseline + GAE) -> the valid steps packed into fewer rows where episodes ended early
(:func:`learning_batch`) -> ``MAMLLoss.adapt`` (one PG step per task) -> collect the
post-update batches the same way with every task's adapted parameters (one
batched policy call per env step) -> :class:`~umrl.optim.trpo.TRPOStep` on ``MAMLLoss``'s forward (the query
surrogate through the inner step), with the KL Hessian-vector product strategy ``trpo.hvp`` names
(:mod:`umrl.optim.meta_hvp`) on ``trpo.hvp_fraction`` of the trajectories. The step's parts run the
``pre_phase`` / ``post_phase`` hooks (:mod:`umrl.trainers.base`) as ``collect`` (twice: pre- and post-update),
``inner_step`` and ``meta_step``.

Metrics of :meth:`MAMLTrainer.step`: ``train/`` return_pre, return_post (mean undiscounted return of the pre/post-update
trajectories), reward_mean/std/min/max (task rewards of the pre-update batch), kl, surrogate_before,
improvement, backtracks (line-search trials; of them rejected_surrogate and rejected_kl, of those nonfinite_kl),
accepted, grad_norm,
step_norm, log_std (θ's action log-std after the meta-step, mean over action dimensions); ``time/`` collect_s
(rollouts + advantages), learn_s (inner adaptation for the post-update policy + TRPO meta-step), inner_s (that
adaptation alone, built with the graph the meta-step differentiates through), the meta-step's parts objective_s
(surrogate and KL through the inner step), direction_s (gradient, HVP set-up, ``trpo.cg_iters`` products), cg_s
(those products alone) and line_search_s, env_steps_per_s (pre + post env steps per second of collect_s),
env_steps. Checkpoints: ``<output_dir>/checkpoints/step_<iteration>.safetensors`` (format in :mod:`umrl.checkpoints.maml`).

Example (tiny sizes; ``umrl.trainers.compose`` reads the defaults in ``umrl/configs/maml.yaml``):
    >>> from umrl.trainers import MAMLTrainer, compose
    >>> cfg = compose("maml", ["proposal=random", "iterations=2", "logger.backend=none"])  # doctest: +SKIP
    >>> trainer = MAMLTrainer(cfg)  # doctest: +SKIP
    >>> metrics = trainer.step()  # one meta-iteration  # doctest: +SKIP
    >>> result = trainer.train()  # the rest, logged and checkpointed  # doctest: +SKIP
"""
from __future__ import annotations

from pathlib import Path

import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase

from umrl.checkpoints import MAML_FORMAT, save_maml_checkpoint
from umrl.checkpoints.folder import Checkpointer
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
from umrl.resume_state import env_state, load_env_state
from umrl.rng import rng_state, seed_everything, set_rng_state
from umrl.rollout import NonFiniteActions, check_cudagraphs, collect, collect_env_steps
from umrl.trainers.base import Trainer
from umrl.trajectories import pack_valid_steps
from umrl.validation import InvalidValue, check_not_diverged, resolve_device

__all__ = ["MAMLTrainer", "build", "collect_batch", "inner_step", "learning_batch", "meta_batch", "meta_step", "train"]


def collect_batch(cfg: DictConfig, proposal, policy, loss: MAMLLoss, adapted: TensorDict | None = None
                  ) -> TensorDictBase:
    """Trajectories of every task ``proposal`` drew (``[T, N, H]``) with their advantages (``loss``'s value
    estimator): with θ (the support), or with every task's ``adapted`` parameters (the query; an inner step
    whose policy acts non-finite is refused, naming ``maml.inner_lr``). ``cfg.sample_by=env_steps`` samples
    each task's first episodes up to N × H env steps (:func:`umrl.rollout.collect_env_steps`),
    ``trajectories`` N trajectories (:func:`umrl.rollout.collect`)."""
    horizon = cfg.env.horizon
    sampling = {"num_tasks": proposal.num_tasks, "horizon": horizon, "cudagraphs": cfg.cudagraphs}
    if cfg.sample_by == "env_steps":
        sampler, sampling["env_steps"] = collect_env_steps, proposal.trajectories_per_task * horizon
    else:
        sampler = collect
    if adapted is None:
        support = loss.value_estimator(sampler(proposal.env, policy, **sampling))
        check_not_diverged({"reward": support["next", "reward"]}, "the pre-update rollouts")
        return support
    try:
        query = sampler(proposal.env, policy, params=adapted.detach(), **sampling)
    except NonFiniteActions as err:  # the inner step diverged
        raise InvalidValue("maml.inner_lr", cfg.maml.inner_lr, "a smaller finite number > 0",
                           note=f"the adapted policy's actions after the inner step: {err.note}") from err
    return loss.value_estimator(query)


def inner_step(loss: MAMLLoss, support: TensorDictBase) -> tuple[TensorDict, float]:
    """Every task's parameters after ``loss.adapt(support)``, built with the graph the meta-step
    differentiates through (second order unless ``maml.first_order``; refused if not finite), and the seconds
    it took (after the device's queued work has finished)."""
    device = next(loss.policy.parameters()).device
    start = device_clock(device)
    with torch.enable_grad():
        adapted = loss.adapt(support)
    check_not_diverged(dict(adapted.items(True, True)), "the adapted parameters (inner step)")
    return adapted, device_clock(device) - start


def learning_batch(loss: MAMLLoss, batch: TensorDictBase) -> TensorDictBase:
    """What the inner step and the meta-step compute on: ``batch``'s valid steps packed into fewer rows where its
    episodes end early (:func:`umrl.trajectories.pack_valid_steps`; a batch of full episodes unchanged)."""
    return pack_valid_steps(batch, loss.tensor_keys.mask)


def meta_batch(cfg: DictConfig, proposal, policy, loss: MAMLLoss, generator: torch.Generator):
    """A fresh meta-batch ``(support, adapted, query, inner_s)``: ``proposal.resample`` draws the tasks, then
    :func:`collect_batch` with θ, :func:`inner_step` and :func:`collect_batch` with the adapted parameters
    (what :meth:`MAMLTrainer.step` does before its meta-step, without its hooks); ``support`` and ``query`` as the
    learning step takes them (:func:`learning_batch`)."""
    proposal.resample(generator)
    support = learning_batch(loss, collect_batch(cfg, proposal, policy, loss))
    adapted, inner_s = inner_step(loss, support)
    return support, adapted, learning_batch(loss, collect_batch(cfg, proposal, policy, loss, adapted)), inner_s


def _iteration_metrics(support: TensorDictBase, query: TensorDictBase, policy, info: dict[str, float], *,
                       batch_s: float, inner_s: float, meta_step_s: float) -> dict[str, float]:
    """A meta-iteration's metrics (module docstring) from its batches, :func:`meta_step`'s ``info`` and its
    times: ``batch_s`` from the iteration's start to the end of the query batch (the inner step included),
    ``inner_s`` the inner step's, ``meta_step_s`` the meta-step's."""
    reward = support["next", "reward"][support["mask"]]
    steps = support["mask"].numel() + query["mask"].numel()  # simulated, episodes past a budget's last one included
    collect_s, learn_s = batch_s - inner_s, meta_step_s + inner_s
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
        "time/objective_s": meta_step_s - phases["direction_s"] - phases["line_search_s"],
        **{f"time/{k}": v for k, v in phases.items()},
        "time/env_steps_per_s": steps / collect_s,
        "time/env_steps": float(steps),
    })
    return metrics


def meta_step(cfg: DictConfig, loss: MAMLLoss, trpo: TRPOStep, support, query, adapted) -> dict[str, float]:
    """TRPO's meta-step through the inner step (``adapted``: :func:`inner_step`'s, with its graph), with the
    KL Hessian-vector product strategy ``trpo`` was built with (``cfg.trpo.hvp`` on ``cfg.trpo.hvp_fraction``
    of the trajectories); updates the policy in place and returns :class:`~umrl.optim.trpo.TRPOStep`'s
    numbers."""
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
    skills = cfg.num_skills or cfg.default_num_skills  # the nulls' meaning: umrl/configs/maml.yaml
    proposal = make_proposal(
        cfg.proposal, cfg.env.name, num_tasks=cfg.meta_batch_size or (skills if cfg.proposal == "oracle" else None),
        trajectories_per_task=cfg.trajectories_per_task, seed=cfg.seed, horizon=cfg.env.horizon,
        num_skills=None if cfg.proposal in ("diayn", "oracle") else skills,
        discriminator_hidden=list(cfg.discriminator_hidden),
        diayn_checkpoint=cfg.diayn_checkpoint if cfg.proposal == "diayn" else None, device=device,
        arena=cfg.env.arena,
    )
    env = proposal.env
    if cfg.cudagraphs:
        check_cudagraphs(env)
    obs_dim, act_dim = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    # the same draw as every method's random init for this seed (scratch's, VIME's), whatever the proposal drew
    policy = make_gaussian_policy(obs_dim, act_dim, hidden=list(cfg.policy.hidden), init_std=cfg.policy.init_std,
                                  learn_std=cfg.policy.learn_std, seed=cfg.seed)
    policy = policy.to(device)  # initialised on the CPU: the same weights on every device
    loss = MAMLLoss(policy, inner_lr=cfg.maml.inner_lr, num_inner_steps=cfg.maml.num_inner_steps,
                    first_order=cfg.maml.first_order, task_loop=cfg.maml.task_loop)
    loss.make_value_estimator(gamma=cfg.advantage.gamma, lmbda=cfg.advantage.lmbda, normalize=cfg.advantage.normalize)
    hvp = make_meta_hvp(cfg.trpo.hvp, loss, fraction=cfg.trpo.hvp_fraction, generator=generator)
    trpo = TRPOStep(loss.params, hvp=hvp, max_kl=cfg.trpo.max_kl, damping=cfg.trpo.damping, cg_iters=cfg.trpo.cg_iters,
                    backtrack_ratio=cfg.trpo.backtrack_ratio, max_backtracks=cfg.trpo.max_backtracks)
    return proposal, policy, loss, trpo


class MAMLTrainer(Trainer):
    """MAML meta-training built from a config (checked against :class:`~umrl.configs.maml.MAMLConfig` first).

    Construction seeds every RNG (``cfg.seed``), builds the proposal, policy, loss and TRPO step
    (:func:`build`) and the checkpointer (``<output_dir>/checkpoints``); with ``cfg.resume`` it restores the
    latest checkpoint (:meth:`load_state_dict`). A config that differs from the checkpoint's beyond
    ``umrl.configs.RESUME_ALLOW`` is refused. :meth:`setup` (run by the first :meth:`step` or :meth:`train`)
    writes the checkpoint of the start (of a fresh run: iteration 0, the initialisation, the meta-training
    ablation's first point) and opens the logger.

    :meth:`step` runs one meta-iteration and returns its metrics; :meth:`train` steps to ``cfg.iterations``,
    logging (``cfg.logger``) and checkpointing (``cfg.checkpoint.every`` and the last; the loop and its hook
    points are :class:`~umrl.trainers.base.Trainer`'s); :meth:`state_dict` holds everything a resumed run
    needs to finish bit-identical to an uninterrupted one: the policy, the counters, every RNG (torch, numpy,
    python, the task generator) and the env's reset noise.

    Attributes: ``cfg`` (validated), ``proposal``, ``policy``, ``loss``, ``trpo``, ``generator`` (task draws
    and the HVP subsample), ``iteration``, ``env_steps``, ``checkpointer``, ``resumed`` (whether construction
    restored a checkpoint: then :meth:`setup` writes none).

    Construction first locks ``output_dir`` until :meth:`close` (:func:`umrl.folder_lock.claim_run_folder`: a folder
    another run uses, or one holding checkpoints while ``cfg.resume`` is false, is refused before any work).

    Nothing process-wide is set: the caller's torch thread count is used (``cfg.num_threads`` is applied by the
    command line, ``recipes/maml.py``, and by the suite's workers; :mod:`umrl.process`).
    """

    name = "maml"
    PHASES = ("collect", "inner_step", "meta_step")
    stop_message = "after meta-iteration {progress} of {budget}"

    @releases_folder_on_error
    def __init__(self, cfg: DictConfig):
        super().__init__()
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
            **({} if cfg.policy.learn_std else {"learn_std": False}),  # absent: learned (files written before it)
        }
        self.iteration, self.env_steps = 0, 0
        # FileNotFoundError says what is missing; ConfigError lists changed keys; ValueError if format or meta differ
        path, state = (MAML_FORMAT.load_for_resume(self.checkpointer, self.meta,
                                                    lambda saved: check_resume(saved, cfg))
                       if cfg.resume else (None, None))
        self.resumed = state is not None
        if state is not None:
            self.restore(path, state)
            check_budget_left("iterations", cfg.iterations, self.iteration, "iterations", self.output_dir)

    @property
    def progress(self) -> int:
        """Meta-iterations done."""
        return self.iteration

    @property
    def budget(self) -> int:
        return self.cfg.iterations

    def _setup(self) -> dict[str, float]:
        if not self.resumed:
            self.save()
        return {}

    def _step(self) -> dict[str, float]:
        """One meta-iteration (module docstring): the policy is updated in place; returns its metrics. Times
        are taken after the device's queued work (CUDA) has finished."""
        cfg, proposal, policy, loss = self.cfg, self.proposal, self.policy, self.loss
        device = next(policy.parameters()).device
        start = device_clock(device)
        proposal.resample(self.generator)
        with self.phase("collect"):
            support = collect_batch(cfg, proposal, policy, loss)
        with self.phase("inner_step"):
            learn_support = learning_batch(loss, support)
            adapted, inner_s = inner_step(loss, learn_support)
        with self.phase("collect"):
            query = collect_batch(cfg, proposal, policy, loss, adapted)
            learn_query = learning_batch(loss, query)
        collected = device_clock(device)
        with self.phase("meta_step"):
            info = meta_step(cfg, loss, self.trpo, learn_support, learn_query, adapted)
        metrics = _iteration_metrics(support, query, policy, info, batch_s=collected - start, inner_s=inner_s,
                                     meta_step_s=device_clock(device) - collected)
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

    def _save(self) -> Path:
        state = self.state_dict()
        return save_maml_checkpoint(self.checkpointer, meta=self.meta, policy=self.policy, iteration=self.iteration,
                                    env_steps=self.env_steps, rng=state["rng"], env=state["env"], config=self.cfg)

    def _result(self) -> dict:
        return {"iteration": self.iteration}

    def _postfix(self, metrics: dict[str, float]) -> dict[str, str]:
        return {"pre": f"{metrics['train/return_pre']:.1f}", "post": f"{metrics['train/return_post']:.1f}",
                "kl": f"{metrics['train/kl']:.4f}", "learn": f"{metrics['time/learn_s']:.1f}s"}

    def _envs(self) -> list:
        return [self.proposal.env]  # closing it ends its worker threads


def train(cfg: DictConfig) -> dict:
    """Meta-train as configured in this process (:class:`MAMLTrainer`, then closed): the last iteration's
    metrics, ``iteration`` and the final ``checkpoint`` path (a run resumed at its budget is refused at
    construction)."""
    trainer = MAMLTrainer(cfg)
    try:
        return trainer.train()
    finally:
        trainer.close()
