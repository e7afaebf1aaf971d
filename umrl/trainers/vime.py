"""VIME pre-training: TRPO on the information-gain bonus alone (the VIME-init baseline's policy).

The command line is ``recipes/vime.py``; from Python, :class:`VIMETrainer` (``step``, ``state_dict``, ``save``,
``log``, ``train``) on a composed config (:func:`umrl.trainers.compose`), or ``umrl.trainers.train("vime", overrides)``.

Each iteration: collect ``env.num_envs`` trajectories of ``env.horizon`` steps with the current policy
(:func:`umrl.rollout.collect`, one batched policy call per step) -> score every transition with
:class:`~umrl.transforms.vime_bonus.VIMEBonus` using the dynamics model *before* it sees them (the reward is the bonus
alone: the CMP's reward is zero) -> add them to the dynamics model's FIFO replay (a TorchRL ``ReplayBuffer`` over a
``LazyTensorStorage``; a share goes to a held-out one) ->
update the running input/target statistics and train the model (:class:`~umrl.objectives.vime.VIMELoss`, Adam) ->
one TRPO step (:class:`umrl.optim.trpo.TRPOStep`) on the importance-ratio surrogate
(:class:`~umrl.objectives.trpo_surrogate.ImportanceSamplingLoss`) with linear-baseline GAE advantages
(:func:`umrl.objectives.policy_gradient.compute_advantages`).

Logged (namespaced): ``bonus/`` info gain and bonus statistics; ``dynamics/`` training loss, log-likelihood, KL to
the prior, held-out log-likelihood and ELBO per transition; ``train/`` the TRPO step's improvement, KL, acceptance,
backtracks (the names MAML's meta-step logs), action_std and frames; ``coverage/`` of the batch's visited states (x-y cells and their area for point_nav and ant, velocity ranges for
half_cheetah), the untrained policy's under ``coverage/initial_*`` and everything visited so far under
``coverage/cumulative_*`` (all from :mod:`umrl.skill_coverage`); ``time/`` env steps/s and seconds per phase (the
TRPO step's direction_s, cg_s and line_search_s too, as in MAML's). The figure ``<output_dir>/figures/coverage.png`` shows the last batch's visited states against the untrained policy's.

Checkpoints: ``<output_dir>/checkpoints/step_<iteration>.safetensors``, format ``umrl.vime.v1`` (documented in
:mod:`umrl.checkpoints.vime`); ``umrl.checkpoints.load_vime_policy(path)`` returns the policy to fine-tune.
``resume=true`` restores the policy, the dynamics model and its optimiser, the bonus normaliser, the transitions,
the counters, every RNG and the env's reset noise (bit-identical to an uninterrupted run).
"""
from __future__ import annotations

import math
import time
from pathlib import Path

import torch
from omegaconf import DictConfig
from tensordict import TensorDict, TensorDictBase
from torchrl.data import LazyTensorStorage, ReplayBuffer, TensorDictReplayBuffer

from umrl.checkpoints import VIME_FORMAT, save_vime_checkpoint
from umrl.checkpoints.folder import Checkpointer
from umrl.checkpoints.format import check_budget_left
from umrl.configs import check_resume, validate
from umrl.configs.vime import VIMEConfig
from umrl.envs import get_env_spec, make_env
from umrl.folder_lock import claim_run_folder, releases_folder_on_error
from umrl.modules.bnn import BayesianDynamics
from umrl.modules.policy import make_gaussian_policy
from umrl.objectives.trpo_surrogate import ImportanceSamplingLoss
from umrl.objectives.vime import VIMELoss
from umrl.optim.trpo import TRPOStep
from umrl.resume_state import env_state, load_env_state, load_replay_buffer_state, replay_buffer_state
from umrl.rng import rng_state, seed_everything, set_rng_state
from umrl.rollout import collect
from umrl.skill_coverage import cumulative_coverage, plot_coverage, state_coverage, visited_states
from umrl.trainers.base import Trainer
from umrl.transforms.vime_bonus import VIMEBonus
from umrl.validation import check_not_diverged, resolve_device

__all__ = ["TRANSITION_KEYS", "VIMETrainer", "heldout_metrics", "train", "train_dynamics", "trpo_update"]

TRANSITION_KEYS = ("observation", "action", ("next", "observation"))
"""What the dynamics model learns from: ``(s, a, s')``."""


def trpo_update(trpo: TRPOStep, loss: ImportanceSamplingLoss, batch: TensorDictBase) -> dict[str, float]:
    """One TRPO step on the importance-ratio surrogate ``-mean(ratio * advantage)`` with the mean KL(old || new)
    over the valid steps (``batch`` is one task's ``[N, H]``)."""

    def closure():
        out = loss(batch)
        return out["loss_objective"], out["trust_region_kl"]

    return trpo(closure)


def train_dynamics(loss_fn: VIMELoss, optimizer, replay: ReplayBuffer, cfg: DictConfig) -> dict[str, float]:
    """``updates_per_iteration`` Adam steps on random minibatches of the replay; mean diagnostics."""
    loss_fn.dataset_size = len(replay)
    logs = []
    for _ in range(cfg.dynamics.updates_per_iteration):
        out = loss_fn(replay.sample(cfg.dynamics.batch_size))
        check_not_diverged({"loss_dynamics": out["loss_dynamics"]}, "dynamics update")
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


class VIMETrainer(Trainer):
    """VIME pre-training built from a config (checked against :class:`~umrl.configs.vime.VIMEConfig` first).

    Construction seeds every RNG (``cfg.seed``), builds the env, the policy, the Bayesian dynamics model with its
    loss, optimiser and replay (a held-out share beside it), the bonus and the TRPO step; with ``cfg.resume`` it
    restores the latest checkpoint (:meth:`load_state_dict`; ``checkpoint.save_replay=true``, the default, makes the
    resumed run finish bit-identical to an uninterrupted one). A config that differs from the checkpoint's beyond
    ``umrl.configs.RESUME_ALLOW`` is refused, and so is a checkpoint already at ``cfg.iterations``.

    Construction first locks ``output_dir`` until :meth:`close` (:func:`umrl.folder_lock.claim_run_folder`: a folder
    another run uses, or one holding checkpoints while ``cfg.resume`` is false, is refused before any work).

    :meth:`step` runs one iteration (module docstring) and returns its metrics; its parts run the
    ``pre_phase`` / ``post_phase`` hooks as ``collect``, ``bonus``, ``dynamics`` and ``policy``. :meth:`train`
    steps to ``cfg.iterations``, logging, checkpointing (``cfg.checkpoint.every`` and the last) and drawing
    the coverage figure (its final :meth:`evaluate`; the loop and its hook points are
    :class:`~umrl.trainers.base.Trainer`'s). Nothing process-wide is set (:mod:`umrl.process`).
    """

    name = "vime"
    PHASES = ("collect", "bonus", "dynamics", "policy")
    stop_message = "after iteration {progress} of {budget}"

    @releases_folder_on_error
    def __init__(self, cfg: DictConfig):
        super().__init__()
        self.cfg = cfg = validate(cfg, VIMEConfig)
        seed_everything(cfg.seed)
        self.device = device = torch.device(resolve_device("device", cfg.device))  # networks, replay, env outputs
        self.output_dir = Path(cfg.output_dir)
        self.checkpointer = Checkpointer(self.output_dir / "checkpoints", keep_all=cfg.checkpoint.keep_all)
        self.folder_lock = claim_run_folder(self.output_dir, resume=cfg.resume, checkpointers=[self.checkpointer])
        self.env = make_env(cfg.env.name, cfg.env.num_envs, seed=cfg.seed, device=device, horizon=cfg.env.horizon,
                            backend=cfg.env.backend)
        obs_dim, act_dim = self.env.observation_spec["observation"].shape[-1], self.env.action_spec.shape[-1]
        # initialised on the CPU (the same weights on every device), then moved
        self.policy = make_gaussian_policy(obs_dim, act_dim, hidden=list(cfg.policy.hidden),
                                           init_std=cfg.policy.init_std, seed=cfg.seed).to(device)
        dyn = cfg.dynamics
        self.dynamics = BayesianDynamics(obs_dim, act_dim, hidden=list(dyn.hidden), prior_std=dyn.prior_std,
                                         likelihood_std=dyn.likelihood_std, init_std=dyn.init_std).to(device)
        self.dynamics_loss = VIMELoss(self.dynamics, dataset_size=1, num_samples=dyn.num_samples)
        self.optimizer = torch.optim.Adam(self.dynamics.parameters(), lr=dyn.lr)
        self.bonus = VIMEBonus(self.dynamics, eta=cfg.bonus.eta, num_samples=cfg.bonus.num_samples,
                               median_window=cfg.bonus.median_window).to(device)
        t = cfg.trpo
        self.surrogate = ImportanceSamplingLoss(self.policy)
        self.surrogate.make_value_estimator(gamma=cfg.advantage.gamma, lmbda=cfg.advantage.lmbda)
        self.trpo = TRPOStep(TensorDict.from_module(self.policy), max_kl=t.max_kl, damping=t.damping,
                             cg_iters=t.cg_iters, backtrack_ratio=t.backtrack_ratio, max_backtracks=t.max_backtracks)
        self.meta = {"env": cfg.env.name, "obs_dim": obs_dim, "act_dim": act_dim,
                     "policy_hidden": list(cfg.policy.hidden), "policy_init_std": cfg.policy.init_std,
                     "dynamics_hidden": list(dyn.hidden), "prior_std": dyn.prior_std,
                     "likelihood_std": dyn.likelihood_std}
        self.counters = {"iteration": 0, "frames": 0}
        self.replay = TensorDictReplayBuffer(storage=LazyTensorStorage(dyn.replay_size, device=device),
                                             batch_size=dyn.batch_size)
        self.holdout = TensorDictReplayBuffer(storage=LazyTensorStorage(dyn.holdout_size, device=device))
        self.initial_states = self.seen = None  # the untrained policy's visited states: the figure's baseline
        self.initial_coverage: dict[str, float] = {}
        self.last_batch: TensorDictBase | None = None
        # FileNotFoundError says what is missing; ConfigError lists changed keys; ValueError if format or meta differ
        path, state = (VIME_FORMAT.load_for_resume(self.checkpointer, self.meta,
                                                    lambda saved: check_resume(saved, cfg))
                       if cfg.resume else (None, None))
        if state is not None:
            self.restore(path, state)
            check_budget_left("iterations", cfg.iterations, self.counters["iteration"], "iterations", self.output_dir)

    @property
    def progress(self) -> int:
        """Iterations done."""
        return self.counters["iteration"]

    @property
    def budget(self) -> int:
        return self.cfg.iterations

    def state_dict(self) -> dict:
        """Everything a resumed run needs: networks, optimiser, bonus normaliser, transitions (with
        ``checkpoint.save_replay``), counters, coverage baselines, every RNG and the env's reset noise."""
        keep = self.cfg.checkpoint.save_replay
        return {
            "policy": self.policy.state_dict(), "dynamics": self.dynamics.state_dict(),
            "dynamics_optimizer": self.optimizer.state_dict(), "median_history": self.bonus.median_history,
            "replay": replay_buffer_state(self.replay) if keep else None,
            "holdout": replay_buffer_state(self.holdout) if keep else None, "counters": dict(self.counters),
            "initial_coverage": self.initial_coverage, "initial_states": self.initial_states, "visited": self.seen,
            "rng": rng_state(), "env": env_state(self.env),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`'s (or a checkpoint's) state."""
        self.policy.load_state_dict(state["policy"])
        self.dynamics.load_state_dict(state["dynamics"])
        self.optimizer.load_state_dict(state["dynamics_optimizer"])
        self.bonus.median_history.copy_(state["median_history"])
        for buffer, stored in ((self.replay, state["replay"]), (self.holdout, state["holdout"])):
            if stored is not None:  # TorchRL's buffer state: contents, write cursor, sampler
                load_replay_buffer_state(buffer, stored)
        self.seen = None if state["visited"] is None else state["visited"].to(self.device)
        self.counters.update(state["counters"])
        self.initial_coverage, self.initial_states = state["initial_coverage"], state["initial_states"]
        set_rng_state(state["rng"])
        load_env_state(self.env, state["env"])

    def _save(self) -> Path:
        state = self.state_dict()
        return save_vime_checkpoint(
            self.checkpointer, meta=self.meta, policy=self.policy, dynamics=self.dynamics,
            dynamics_optimizer=self.optimizer, median_history=state["median_history"], replay=state["replay"],
            holdout=state["holdout"], counters=self.counters, initial_coverage=self.initial_coverage,
            initial_states=self.initial_states, visited=self.seen, rng=state["rng"], env=state["env"],
            config=self.cfg)

    def _step(self) -> dict[str, float]:
        """One iteration: collect, score with the bonus, train the dynamics model, one TRPO step; its metrics."""
        cfg, dyn = self.cfg, self.cfg.dynamics
        tic = time.perf_counter()
        with self.phase("collect"):
            batch = collect(self.env, self.policy, num_tasks=1, horizon=cfg.env.horizon)[0]  # [N, H]
        collect_s = time.perf_counter() - tic
        coverage = state_coverage(batch, cfg.env.name, cfg.coverage.cell_size)
        self.seen, cumulative = cumulative_coverage(self.seen, batch, cfg.env.name, cfg.coverage.cell_size)
        if self.counters["iteration"] == 0:
            self.initial_coverage, self.initial_states = coverage, visited_states(batch, cfg.env.name).cpu()

        tic = time.perf_counter()
        with self.phase("bonus"):
            # ("next", "reward") <- 0 + eta * info gain / median, from the model before it sees them
            self.bonus(batch)
        bonus_s = time.perf_counter() - tic
        if cfg.bonus.shuffle:  # control run: same bonus values, no link to the transitions that earned them
            reward = batch["next", "reward"]
            reward[batch["mask"]] = reward[batch["mask"]][torch.randperm(int(batch["mask"].sum()))]
        valid = batch[batch["mask"]].select(*TRANSITION_KEYS)
        held = (torch.rand(valid.shape[0]) < dyn.holdout_fraction).to(valid.device)  # CPU draw: same split anywhere
        for buffer, part in ((self.replay, valid[~held]), (self.holdout, valid[held])):
            if part.shape[0]:
                buffer.extend(part)

        tic = time.perf_counter()
        with self.phase("dynamics"):
            self.dynamics.update_normalizer(*(valid[k] for k in TRANSITION_KEYS))
            dyn_metrics = train_dynamics(self.dynamics_loss, self.optimizer, self.replay, cfg)
            if len(self.holdout):
                dyn_metrics.update(heldout_metrics(self.dynamics_loss, self.holdout[:]))
        dynamics_s = time.perf_counter() - tic

        tic = time.perf_counter()
        with self.phase("policy"):
            self.surrogate.value_estimator(batch)
            trpo_info = trpo_update(self.trpo, self.surrogate, batch)
        policy_s = time.perf_counter() - tic

        self.counters["iteration"] += 1
        self.counters["frames"] += batch.numel()
        self.last_batch = batch
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
            **{f"coverage/initial_{k}": v for k, v in self.initial_coverage.items()},
            "time/env_steps_per_s": batch.numel() / max(collect_s, 1e-9), "time/collect_s": collect_s,
            "time/bonus_s": bonus_s, "time/dynamics_s": dynamics_s, "time/policy_s": policy_s,
            "time/elapsed_s": time.perf_counter() - self.start_time, "train/frames": self.counters["frames"],
        }
        if not all(math.isfinite(v) for v in metrics.values()):
            raise FloatingPointError(f"non-finite metrics at iteration {self.counters['iteration']}: "
                                     f"{ {k: v for k, v in metrics.items() if not math.isfinite(v)} }")
        return metrics

    def plot_coverage(self) -> Path:
        """``<output_dir>/figures/coverage.png``: the last batch's visited states against the untrained policy's."""
        path = self.output_dir / "figures" / "coverage.png"
        plot_coverage(visited_states(self.last_batch, self.cfg.env.name), path,
                      eval_tasks=get_env_spec(self.cfg.env.name).eval_tasks(), baseline=self.initial_states,
                      label="VIME policy", baseline_label="initial policy",
                      title=f"VIME {self.cfg.env.name}: visited states")
        return path

    def _evaluate(self, final: bool) -> dict[str, float]:
        """The coverage figure (:meth:`plot_coverage`) once a batch was collected; no metrics (the coverage
        ones come with every step). It draws no random numbers."""
        if self.initial_states is not None and self.last_batch is not None:
            self.plot_coverage()
        return {}

    def _postfix(self, metrics: dict[str, float]) -> dict[str, str]:
        shown = ("coverage/cells", "coverage/velocity_range", "dynamics/heldout_log_likelihood")
        return {k.split("/")[-1]: f"{metrics[k]:.3g}" for k in shown if k in metrics}

    def _envs(self) -> list:
        return [self.env]


def train(cfg: DictConfig) -> dict:
    """Run VIME pre-training as configured in this process (:class:`VIMETrainer`, then closed): the last metrics
    and the checkpoint path."""
    trainer = VIMETrainer(cfg)
    try:
        return trainer.train()
    finally:
        trainer.close()
