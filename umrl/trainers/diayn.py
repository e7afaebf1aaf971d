"""DIAYN on a reward-free env: skill-conditioned SAC + a skill discriminator (the UMRL task proposal).

The command line is ``recipes/diayn.py``; from Python, :class:`DIAYNTrainer` (``step``, ``checkpoint``, ``log``,
``train``) on a composed config (:func:`umrl.trainers.compose`), or ``umrl.trainers.train("diayn", overrides)``.

Data flow: ``make_env`` -> ``SkillTransform`` (one uniform one-hot skill per episode) -> ``DiscriminatorReward``
(log D(z|s') + log K, for the logged returns) -> TorchRL ``Collector`` -> replay buffer -> ``DIAYNLoss`` (relabels
every sampled batch with the current discriminator, SAC + discriminator cross-entropy) -> ``DIAYNUpdate`` (Adam steps,
target Q-networks by ``SoftUpdate``; ``optim.compile`` / ``optim.cudagraphs`` on a GPU).

Logged (namespaced): ``train/`` losses, ``discriminator_accuracy`` (on replay samples), ``pseudo_reward``,
``entropy``, ``episode_return`` (undiscounted pseudo-return of finished episodes); ``eval/`` on fresh rollouts of
every skill: ``final_state_accuracy`` (argmax D(z|s_T) == z), spread of the skills' end points
(``end_pairwise_distance``, ``centroid_pairwise_distance``, ``centroid_hull_area`` in 2-D, ``centroid_std``/``range``
for half_cheetah's velocities), ``task_distance_median``/``max`` (from each held-out evaluation task to the nearest
skill centroid), the same for a uniformly random policy under ``eval/random_*`` (once);
``time/`` env steps/s, updates/s, elapsed seconds. The coverage figure goes to ``<output_dir>/figures/``.

Checkpoints: ``<output_dir>/checkpoints/step_<frames>.pt`` every ``checkpoint.every`` frames and at the end, format
``umrl.diayn.v1`` documented in :mod:`umrl.checkpoints.diayn`; load the results with
``umrl.checkpoints.load_discriminator(path)`` -> (D, num_skills, obs_dim) and ``load_skill_policy(path)`` ->
(actor, num_skills, obs_dim). ``resume=true`` restores networks, optimisers, counters, the replay buffer, every RNG,
the envs' reset noise and the collector's trajectory counter: the resumed run finishes bit-identical to an
uninterrupted one, in every tensor of its checkpoint (see :func:`train`).
"""
from __future__ import annotations

import time
from pathlib import Path

import torch
import tqdm
from omegaconf import DictConfig
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import RewardSum

from umrl.checkpoints.diayn import DIAYN_FORMAT, check_resumable, save_diayn_checkpoint
from umrl.checkpoints.format import check_budget_left
from umrl.configs import RESUME_ALLOW, check_resume, validate
from umrl.configs.diayn import DIAYNConfig
from umrl.envs import get_env_spec, make_env
from umrl.envs.threads import batches_beside_physics
from umrl.modules.discriminator import make_discriminator
from umrl.modules.sac import make_skill_actor, make_skill_qvalue
from umrl.objectives.diayn import DIAYNLoss, DIAYNUpdate, make_diayn_optimizers
from umrl.runtime import (
    Checkpointer,
    check_finite,
    close_logger,
    env_state,
    isolated_rng,
    load_env_state,
    load_replay_buffer_state,
    log_image,
    log_metrics,
    make_logger,
    replay_buffer_state,
    rng_state,
    seed_everything,
    set_rng_state,
)
from umrl.skill_coverage import coverage_metrics, evaluate_skills, plot_coverage
from umrl.transforms.discriminator_reward import DiscriminatorReward
from umrl.transforms.skill import SkillTransform
from umrl.validation import resolve_device

__all__ = ["DIAYNTrainer", "evaluate", "make_skill_env", "resolve_num_skills", "train"]


def resolve_num_skills(cfg: DictConfig) -> int:
    """``num_skills``, or the env's default (:attr:`umrl.envs.EnvSpec.num_skills`) when it is null."""
    return cfg.num_skills if cfg.num_skills is not None else get_env_spec(cfg.env.name).num_skills


def make_skill_env(cfg: DictConfig, num_envs: int, num_skills: int, seed: int, discriminator=None):
    env = make_env(cfg.env.name, num_envs, seed=seed, device=resolve_device("device", cfg.device), horizon=cfg.env.horizon,
                   backend=cfg.env.backend)
    env.append_transform(SkillTransform(num_skills))
    if discriminator is not None:
        env.append_transform(DiscriminatorReward(discriminator, num_skills))
        env.append_transform(RewardSum())
    return env


def evaluate(cfg, env, actor, discriminator, num_skills, step, figure_path, logger, baseline) -> dict:
    """Fresh rollouts of every skill: coverage metrics, final-state accuracy, the figure at ``figure_path``; the
    training's random generators do not move (a resumed run draws what an uninterrupted one draws)."""
    with isolated_rng():
        result = evaluate_skills(env, actor, env_name=cfg.env.name, num_skills=num_skills,
                                 episodes_per_skill=cfg.eval.episodes_per_skill, horizon=cfg.env.horizon)
    eval_tasks = get_env_spec(cfg.env.name).eval_tasks()
    metrics = {f"eval/{k}": v for k, v in coverage_metrics(result, num_skills, discriminator, eval_tasks).items()}
    figure = plot_coverage(result["end_point"], figure_path, eval_tasks=eval_tasks, skills=result["skill"],
                           baseline=baseline["end_point"],
                           title=f"DIAYN {cfg.env.name}, {num_skills} skills, {step} env steps")
    log_image(logger, "eval/skill_coverage", figure, step)
    return metrics


class DIAYNTrainer:
    """DIAYN built from a config (checked against :class:`~umrl.configs.diayn.DIAYNConfig` first).

    Construction seeds every RNG (``cfg.seed``), builds the networks, the loss and its update, the training and
    evaluation envs, the collector and the replay buffer, evaluates a uniformly random policy (logged once under
    ``eval/random_*``), and with ``cfg.resume`` restores the latest checkpoint (:meth:`load_state_dict`).

    :meth:`step` takes one collector batch: into the replay, then ``optim.updates_per_frame`` updates per new frame,
    an evaluation when one is due; it returns the batch's metrics. :meth:`checkpoint` saves and restarts the
    collector's episodes (TorchRL cannot serialise in-flight episodes, so an uninterrupted run restarts them at every
    checkpoint exactly as a resumed one does; with the default batch of one episode per env copy nothing is cut).
    :meth:`train` steps to ``collector.total_frames``, logging, checkpointing every ``checkpoint.every`` frames and
    at the end, then evaluates the final skills. A resumed run finishes bit-identical to an uninterrupted one; a
    config that differs from the checkpoint's beyond ``umrl.configs.RESUME_ALLOW`` (or in ``checkpoint.every``) is
    refused. Nothing process-wide is set (:mod:`umrl.process`).
    """

    def __init__(self, cfg: DictConfig):
        self.cfg = cfg = validate(cfg, DIAYNConfig)
        self.num_skills = num_skills = resolve_num_skills(cfg)
        seed_everything(cfg.seed)
        device = torch.device(resolve_device("device", cfg.device))  # networks, loss, replay storage and envs
        self.output_dir = Path(cfg.output_dir)
        self.checkpointer = Checkpointer(self.output_dir / "checkpoints", keep_all=cfg.checkpoint.keep_all)

        # --- networks, loss, optimisers ---------------------------------------------------------------
        env_spec = get_env_spec(cfg.env.name)
        obs_dim, act_dim = env_spec.obs_dim, env_spec.act_dim
        hidden, disc_hidden = list(cfg.network.hidden), list(cfg.network.discriminator_hidden)
        disc_dims = (None if cfg.network.discriminator_input_dims is None
                     else list(cfg.network.discriminator_input_dims))
        self.meta = {"env": cfg.env.name, "obs_dim": obs_dim, "act_dim": act_dim, "num_skills": num_skills,
                     "hidden": hidden, "discriminator_hidden": disc_hidden,
                     "discriminator_observation_key": ["observation"],
                     "discriminator_input_dims": disc_dims}
        # FileNotFoundError says what is missing; ConfigError lists changed keys; ValueError if format or meta differ
        # the collector restarts its episodes at every checkpoint: a changed checkpoint.every would continue another
        # run
        allow = [key for key in RESUME_ALLOW if key != "checkpoint.every"]
        state = (DIAYN_FORMAT.load_for_resume(self.checkpointer, self.meta,
                                              lambda saved: check_resume(saved, cfg, allow))
                 if cfg.resume else None)
        if state is not None:
            check_resumable(state, self.checkpointer.latest())
        # initialised on the CPU (the same weights on every device), then moved before the loss copies their parameters
        self.actor = make_skill_actor(obs_dim, num_skills, act_dim, hidden=hidden).to(device)
        self.discriminator = make_discriminator(obs_dim, num_skills, hidden=disc_hidden,
                                                input_dims=disc_dims).to(device)
        qvalue = make_skill_qvalue(obs_dim, num_skills, act_dim, hidden=hidden).to(device)
        self.loss = DIAYNLoss(self.actor, qvalue, self.discriminator, num_skills=num_skills,
                              alpha_init=cfg.optim.alpha, fixed_alpha=cfg.optim.fixed_alpha,
                              target_entropy=-float(act_dim)).to(device)
        self.loss.make_value_estimator(gamma=cfg.optim.gamma)
        self.optimizers = make_diayn_optimizers(self.loss, lr=cfg.optim.lr, discriminator_lr=cfg.optim.discriminator_lr,
                                                capturable=cfg.optim.cudagraphs)
        # before the restore: TorchRL's SoftUpdate copies the online Q-networks into the targets when it is built
        self.update = DIAYNUpdate(self.loss, self.optimizers, tau=cfg.optim.tau, compile=cfg.optim.compile,
                                  cudagraphs=cfg.optim.cudagraphs)
        self.counters = {"frames": 0, "updates": 0, "next_eval": cfg.eval.every,
                         "next_checkpoint": cfg.checkpoint.every, "update_credit": 0.0}
        if state is not None:
            self.loss.load_state_dict(state["loss"])
            for name, optimizer in self.optimizers.items():
                optimizer.load_state_dict(state["optimizers"][name])
            self.counters.update(state["counters"])
            check_budget_left("collector.total_frames", cfg.collector.total_frames, self.counters["frames"], "frames",
                              self.output_dir)

        # --- data -------------------------------------------------------------------------------------
        self.env = make_skill_env(cfg, cfg.env.num_envs, num_skills, cfg.seed, self.discriminator)
        self.eval_env = make_skill_env(cfg, num_skills * cfg.eval.episodes_per_skill, num_skills, cfg.seed + 10_000)
        remaining = cfg.collector.total_frames - self.counters["frames"]
        self.collector = Collector(
            self.env, self.actor, frames_per_batch=cfg.collector.frames_per_batch, total_frames=remaining,
            init_random_frames=max(0, cfg.collector.init_random_frames - self.counters["frames"]),
            auto_register_policy_transforms=False,
        )
        self.buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(cfg.replay_buffer.size, device=device),
                                             batch_size=cfg.replay_buffer.batch_size)
        self.warmup = max(cfg.collector.init_random_frames, cfg.replay_buffer.batch_size)

        self.logger = make_logger(cfg.logger, exp_name=cfg.logger.exp_name, config=cfg, log_dir=self.output_dir)
        with isolated_rng():
            self.baseline = evaluate_skills(self.eval_env, None, env_name=cfg.env.name, num_skills=num_skills,
                                            episodes_per_skill=cfg.eval.episodes_per_skill, horizon=cfg.env.horizon)
        if state is not None and "random_metrics" in state:  # scored by the initial discriminator, logged once
            self.random_metrics = dict(state["random_metrics"])
        else:
            self.random_metrics = {f"eval/random_{k}": v for k, v in coverage_metrics(
                self.baseline, num_skills, self.discriminator, env_spec.eval_tasks()).items()}
            log_metrics(self.logger, self.random_metrics, self.counters["frames"])
        if state is not None:  # after everything that draws while setting up: the loop starts where the saved one stood
            self.load_state_dict(state)
        self._batches = batches_beside_physics(self.collector, self.env)
        self.start_time = time.perf_counter()

    @property
    def done(self) -> bool:
        """Whether the budget (``collector.total_frames``) is reached."""
        return self.counters["frames"] >= self.cfg.collector.total_frames

    def state_dict(self) -> dict:
        """Networks (the loss's), optimisers, counters, the random policy's metrics, the replay buffer, every RNG,
        both envs' reset noise and the collector's trajectory counter."""
        return {"loss": self.loss.state_dict(),
                "optimizers": {name: opt.state_dict() for name, opt in self.optimizers.items()},
                "counters": dict(self.counters), "random_metrics": dict(self.random_metrics),
                "replay": replay_buffer_state(self.buffer), "rng": rng_state(),
                "envs": {"train": env_state(self.env), "eval": env_state(self.eval_env)},
                "collector": {"traj_pool": self.collector.state_dict()["traj_pool"]}}

    def load_state_dict(self, state: dict) -> None:
        """Restore the replay buffer, the envs' and RNGs' state and the collector's trajectory counter, and restart
        the collector's episodes as the saved run did right after saving (networks, optimisers and counters are
        restored at construction, before the collector is built from them)."""
        load_replay_buffer_state(self.buffer, state["replay"])
        load_env_state(self.env, state["envs"]["train"])
        load_env_state(self.eval_env, state["envs"]["eval"])
        set_rng_state(state["rng"])
        if "collector" in state:  # absent before the key: the resumed run's ("collector", "traj_ids") restart at 0
            # the counter alone: TorchRL's Collector.load_state_dict would also reset the frame count of this
            # collector (built for the remaining frames) and start trajectories before the reset below starts them
            self.collector._traj_pool.load_state_dict(state["collector"]["traj_pool"])
        self.collector.reset()

    def checkpoint(self) -> Path:
        """Save the current state and restart the collector's episodes (what a run resumed from it does)."""
        state = self.state_dict()
        path = save_diayn_checkpoint(
            self.checkpointer, meta=self.meta, actor=self.actor, discriminator=self.discriminator, loss=self.loss,
            optimizers=self.optimizers, counters=self.counters, random_metrics=self.random_metrics,
            replay=state["replay"], rng=state["rng"], envs=state["envs"], collector=state["collector"], config=self.cfg)
        self.collector.reset()
        return path

    def evaluate(self, figure_path: Path) -> dict[str, float]:
        """Fresh rollouts of every skill (:func:`evaluate`) at the current frame count."""
        return evaluate(self.cfg, self.eval_env, self.actor, self.discriminator, self.num_skills,
                        self.counters["frames"], figure_path, self.logger, self.baseline)

    def step(self) -> dict[str, float]:
        """One collector batch: replay, updates, an evaluation when due; its metrics."""
        cfg, counters = self.cfg, self.counters
        collect_start = time.perf_counter()
        data = next(self._batches).reshape(-1)
        collect_time = time.perf_counter() - collect_start
        self.buffer.extend(data)
        counters["frames"] += data.numel()

        update_start, logs = time.perf_counter(), []
        if len(self.buffer) >= self.warmup:
            counters["update_credit"] += data.numel() * cfg.optim.updates_per_frame
            for _ in range(int(counters["update_credit"])):
                logs.append(self.update(self.buffer.sample()))
            counters["update_credit"] -= int(counters["update_credit"])
        if logs:  # once per batch of updates: a per-update check would wait on the GPU after every update
            stacked = torch.stack(logs)
            check_finite({k: v for k, v in stacked.items() if k.startswith("loss_")},
                         f"DIAYN updates {counters['updates']}..{counters['updates'] + len(logs) - 1}")
            counters["updates"] += len(logs)
        update_time = time.perf_counter() - update_start

        metrics = {"time/env_steps_per_s": data.numel() / max(collect_time, 1e-9),
                   "time/elapsed_s": time.perf_counter() - self.start_time, "train/frames": counters["frames"],
                   "train/updates": counters["updates"]}
        if logs:
            mean = stacked.float().mean()
            metrics.update({f"train/{k}": float(v) for k, v in mean.items()})
            metrics["time/updates_per_s"] = len(logs) / max(update_time, 1e-9)
        finished = data["next", "done"].squeeze(-1)
        if finished.any():
            metrics["train/episode_return"] = float(data["next", "episode_reward"][finished].mean())
        if counters["frames"] >= counters["next_eval"]:
            metrics.update(self.evaluate(self.output_dir / "figures" / f"skill_coverage_{counters['frames']}.png"))
            counters["next_eval"] += cfg.eval.every
        return metrics

    def log(self, metrics: dict[str, float]) -> None:
        """Send ``metrics`` to the configured logger at the current frame count."""
        log_metrics(self.logger, metrics, self.counters["frames"])

    def train(self) -> dict:
        """Step to ``collector.total_frames`` (logging, checkpointing every ``checkpoint.every`` frames and at the
        end), then evaluate the final skills; returns the last metrics, the final evaluation, the random policy's
        and the ``checkpoint`` path."""
        cfg, counters = self.cfg, self.counters
        progress = tqdm.tqdm(total=cfg.collector.total_frames, initial=counters["frames"], disable=not cfg.progress,
                             unit="frames", desc=f"DIAYN {cfg.env.name}")
        metrics, path = {}, None
        while not self.done:
            before = counters["frames"]
            metrics = self.step()
            progress.update(counters["frames"] - before)
            self.log(metrics)
            progress.set_postfix({k.split("/")[-1]: f"{v:.3g}" for k, v in metrics.items()
                                  if k in ("train/discriminator_accuracy", "train/pseudo_reward",
                                           "eval/final_state_accuracy")})
            due = counters["frames"] >= counters["next_checkpoint"]
            if due or self.done:  # every checkpoint.every frames, and the end
                counters["next_checkpoint"] += cfg.checkpoint.every * due
                path = self.checkpoint()
        progress.close()
        final = self.evaluate(self.output_dir / "figures" / "skill_coverage.png")
        self.log(final)
        return {**metrics, **final, **self.random_metrics, "checkpoint": str(path)}

    def close(self) -> None:
        """Shut the collector down and close both envs."""
        self.collector.shutdown()
        self.env.close()
        self.eval_env.close()
        close_logger(self.logger)


def train(cfg: DictConfig) -> dict:
    """Run DIAYN as configured in this process (:class:`DIAYNTrainer`, then closed): the last logged metrics (also
    the final evaluation's) and the checkpoint path."""
    trainer = DIAYNTrainer(cfg)
    try:
        return trainer.train()
    finally:
        trainer.close()
