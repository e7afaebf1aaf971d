"""DIAYN on a reward-free env: skill-conditioned SAC + a skill discriminator (the UMRL task proposal).

    python recipes/diayn.py env.name=point_nav                       # 50 skills, PROTOCOL.md defaults
    python recipes/diayn.py env.name=half_cheetah logger.backend=csv
    python recipes/diayn.py env.name=point_nav resume=true           # continue from the latest checkpoint

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
(actor, num_skills, obs_dim). ``resume=true`` restores networks, optimisers, counters, the replay buffer, every RNG and
the envs' reset noise: the resumed run finishes bit-identical to an uninterrupted one (see :func:`train`).
"""
from __future__ import annotations

import logging
import time
from pathlib import Path

import hydra
import torch
import tqdm
from omegaconf import DictConfig
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer
from torchrl.envs import RewardSum

from recipes import register_help_text
from umrl.checkpoints.diayn import DIAYN_FORMAT, check_resumable, save_diayn_checkpoint
from umrl.configs import RESUME_ALLOW, check_resume, validate
from umrl.configs.diayn import DIAYNConfig
from umrl.envs import get_env_spec, make_env
from umrl.envs.threads import batches_beside_physics
from umrl.heap import keep_freed_memory
from umrl.modules.discriminator import make_discriminator
from umrl.modules.sac import make_skill_actor, make_skill_qvalue
from umrl.objectives.diayn import DIAYNLoss, DIAYNUpdate, make_diayn_optimizers
from umrl.runtime import (
    Checkpointer,
    check_finite,
    env_state,
    finishing_loggers,
    isolated_rng,
    load_env_state,
    load_replay_buffer_state,
    log_image,
    log_location,
    log_metrics,
    make_logger,
    replay_buffer_state,
    rng_state,
    run_summary,
    seed_everything,
    set_rng_state,
)
from umrl.skill_coverage import coverage_metrics, evaluate_skills, plot_coverage
from umrl.transforms.discriminator_reward import DiscriminatorReward
from umrl.transforms.skill import SkillTransform
from umrl.validation import resolve_device


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


@finishing_loggers()
def train(cfg: DictConfig) -> dict:
    """Run DIAYN as configured (checked against :class:`~umrl.configs.diayn.DIAYNConfig` first); return the last
    logged metrics (also the final evaluation).

    ``resume=true`` restores networks, optimisers, counters, the replay buffer (its TorchRL ``state_dict``), every
    RNG and the envs' reset noise, and finishes bit-identical to an uninterrupted run: TorchRL cannot serialise
    in-flight episodes, so the collector restarts its episodes after every checkpoint, in an uninterrupted run
    exactly as in a resumed one (with the default batch of one episode per env copy, a checkpoint falls on an
    episode boundary and nothing is cut). A config that differs from the checkpoint's beyond
    ``umrl.configs.RESUME_ALLOW`` is refused."""
    cfg = validate(cfg, DIAYNConfig)
    num_skills = resolve_num_skills(cfg)
    torch.set_num_threads(cfg.num_threads)
    keep_freed_memory()
    seed_everything(cfg.seed)
    device = torch.device(resolve_device("device", cfg.device))  # networks, loss, replay storage and envs
    out_dir = Path(cfg.output_dir)
    checkpointer = Checkpointer(out_dir / "checkpoints", keep_all=cfg.checkpoint.keep_all)

    # --- networks, loss, optimisers -------------------------------------------------------------------
    env_spec = get_env_spec(cfg.env.name)
    obs_dim, act_dim = env_spec.obs_dim, env_spec.act_dim
    hidden, disc_hidden = list(cfg.network.hidden), list(cfg.network.discriminator_hidden)
    disc_dims = None if cfg.network.discriminator_input_dims is None else list(cfg.network.discriminator_input_dims)
    meta = {"env": cfg.env.name, "obs_dim": obs_dim, "act_dim": act_dim, "num_skills": num_skills,
            "hidden": hidden, "discriminator_hidden": disc_hidden,
            "discriminator_observation_key": ["observation"],
            "discriminator_input_dims": disc_dims}
    # FileNotFoundError says what is missing; ConfigError lists changed keys; ValueError if format or meta differ
    # the collector restarts its episodes at every checkpoint: a changed checkpoint.every would continue another run
    allow = [key for key in RESUME_ALLOW if key != "checkpoint.every"]
    state = (DIAYN_FORMAT.load_for_resume(checkpointer, meta, lambda saved: check_resume(saved, cfg, allow))
             if cfg.resume else None)
    if state is not None:
        check_resumable(state, checkpointer.latest())
    # initialised on the CPU (the same weights on every device), then moved before the loss copies their parameters
    actor = make_skill_actor(obs_dim, num_skills, act_dim, hidden=hidden).to(device)
    discriminator = make_discriminator(obs_dim, num_skills, hidden=disc_hidden,
                                       input_dims=disc_dims).to(device)
    qvalue = make_skill_qvalue(obs_dim, num_skills, act_dim, hidden=hidden).to(device)
    loss = DIAYNLoss(actor, qvalue, discriminator, num_skills=num_skills, alpha_init=cfg.optim.alpha,
                     fixed_alpha=cfg.optim.fixed_alpha, target_entropy=-float(act_dim)).to(device)
    loss.make_value_estimator(gamma=cfg.optim.gamma)
    optimizers = make_diayn_optimizers(loss, lr=cfg.optim.lr, discriminator_lr=cfg.optim.discriminator_lr,
                                       capturable=cfg.optim.cudagraphs)
    # before the restore: TorchRL's SoftUpdate copies the online Q-networks into the targets when it is built
    update = DIAYNUpdate(loss, optimizers, tau=cfg.optim.tau, compile=cfg.optim.compile, cudagraphs=cfg.optim.cudagraphs)
    counters = {"frames": 0, "updates": 0, "next_eval": cfg.eval.every, "next_checkpoint": cfg.checkpoint.every,
                "update_credit": 0.0}
    if state is not None:
        loss.load_state_dict(state["loss"])
        for name, optimizer in optimizers.items():
            optimizer.load_state_dict(state["optimizers"][name])
        counters.update(state["counters"])

    def save() -> Path:
        return save_diayn_checkpoint(checkpointer, meta=meta, actor=actor, discriminator=discriminator, loss=loss,
                                     optimizers=optimizers, counters=counters, replay=replay_buffer_state(buffer),
                                     rng=rng_state(), envs={"train": env_state(env), "eval": env_state(eval_env)},
                                     config=cfg)

    # --- data -----------------------------------------------------------------------------------------
    env = make_skill_env(cfg, cfg.env.num_envs, num_skills, cfg.seed, discriminator)
    eval_env = make_skill_env(cfg, num_skills * cfg.eval.episodes_per_skill, num_skills, cfg.seed + 10_000)
    remaining = cfg.collector.total_frames - counters["frames"]
    if remaining <= 0:
        raise ValueError(f"nothing to do: the checkpoint already has {counters['frames']} frames >= "
                         f"collector.total_frames={cfg.collector.total_frames}; raise collector.total_frames.")
    collector = Collector(
        env, actor, frames_per_batch=cfg.collector.frames_per_batch, total_frames=remaining,
        init_random_frames=max(0, cfg.collector.init_random_frames - counters["frames"]),
        auto_register_policy_transforms=False,
    )
    buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(cfg.replay_buffer.size, device=device),
                                    batch_size=cfg.replay_buffer.batch_size)
    warmup = max(cfg.collector.init_random_frames, cfg.replay_buffer.batch_size)

    logger = make_logger(cfg.logger, exp_name=cfg.logger.exp_name, config=cfg, log_dir=out_dir)
    with isolated_rng():
        baseline = evaluate_skills(eval_env, None, env_name=cfg.env.name, num_skills=num_skills,
                                   episodes_per_skill=cfg.eval.episodes_per_skill, horizon=cfg.env.horizon)
    random_metrics = {f"eval/random_{k}": v for k, v in coverage_metrics(
        baseline, num_skills, discriminator, env_spec.eval_tasks()).items()}
    log_metrics(logger, random_metrics, counters["frames"])
    if state is not None:  # after everything that draws while setting up: the loop starts where the saved one stood
        load_replay_buffer_state(buffer, state["replay"])
        load_env_state(env, state["envs"]["train"])
        load_env_state(eval_env, state["envs"]["eval"])
        set_rng_state(state["rng"])
        collector.reset()  # as the saved run did right after saving

    # --- loop -----------------------------------------------------------------------------------------
    progress = tqdm.tqdm(total=cfg.collector.total_frames, initial=counters["frames"], disable=not cfg.progress,
                         unit="frames", desc=f"DIAYN {cfg.env.name}")
    metrics, start, path = {}, time.perf_counter(), None
    collect_start = time.perf_counter()
    for data in batches_beside_physics(collector, env):
        collect_time = time.perf_counter() - collect_start
        data = data.reshape(-1)
        buffer.extend(data)
        counters["frames"] += data.numel()
        progress.update(data.numel())

        update_start, logs = time.perf_counter(), []
        if len(buffer) >= warmup:
            counters["update_credit"] += data.numel() * cfg.optim.updates_per_frame
            for _ in range(int(counters["update_credit"])):
                logs.append(update(buffer.sample()))
            counters["update_credit"] -= int(counters["update_credit"])
        if logs:  # once per batch of updates: a per-update check would wait on the GPU after every update
            stacked = torch.stack(logs)
            check_finite({k: v for k, v in stacked.items() if k.startswith("loss_")},
                         f"DIAYN updates {counters['updates']}..{counters['updates'] + len(logs) - 1}")
            counters["updates"] += len(logs)
        update_time = time.perf_counter() - update_start

        metrics = {"time/env_steps_per_s": data.numel() / max(collect_time, 1e-9),
                   "time/elapsed_s": time.perf_counter() - start, "train/frames": counters["frames"],
                   "train/updates": counters["updates"]}
        if logs:
            mean = stacked.float().mean()
            metrics.update({f"train/{k}": float(v) for k, v in mean.items()})
            metrics["time/updates_per_s"] = len(logs) / max(update_time, 1e-9)
        finished = data["next", "done"].squeeze(-1)
        if finished.any():
            metrics["train/episode_return"] = float(data["next", "episode_reward"][finished].mean())
        if counters["frames"] >= counters["next_eval"]:
            figure_path = out_dir / "figures" / f"skill_coverage_{counters['frames']}.png"
            metrics.update(evaluate(cfg, eval_env, actor, discriminator, num_skills, counters["frames"], figure_path,
                                    logger, baseline))
            counters["next_eval"] += cfg.eval.every
        log_metrics(logger, metrics, counters["frames"])
        progress.set_postfix({k.split("/")[-1]: f"{v:.3g}" for k, v in metrics.items()
                              if k in ("train/discriminator_accuracy", "train/pseudo_reward",
                                       "eval/final_state_accuracy")})
        due = counters["frames"] >= counters["next_checkpoint"]
        if due or counters["frames"] >= cfg.collector.total_frames:  # every checkpoint.every frames, and the end
            counters["next_checkpoint"] += cfg.checkpoint.every * due
            path = save()
            collector.reset()  # what a run resumed from this checkpoint does: both step the same episodes
        collect_start = time.perf_counter()
    collector.shutdown()
    progress.close()

    final = evaluate(cfg, eval_env, actor, discriminator, num_skills, counters["frames"],
                     out_dir / "figures" / "skill_coverage.png", logger, baseline)
    log_metrics(logger, final, counters["frames"])
    env.close()
    eval_env.close()
    return {**metrics, **final, **random_metrics, "checkpoint": str(path)}


SUMMARY_KEYS = ("train/frames", "train/updates", "train/discriminator_accuracy", "eval/final_state_accuracy",
                "eval/random_final_state_accuracy")
"""What the command line prints when a run ends (every metric is in the logs)."""


@hydra.main(version_base="1.3", config_path="config", config_name="diayn")
def main(cfg: DictConfig) -> None:
    result = train(cfg)
    logging.getLogger(__name__).info(run_summary(f"diayn {cfg.env.name} finished", result, SUMMARY_KEYS,
                                                 log_location(cfg.logger, cfg.output_dir)))


if __name__ == "__main__":
    register_help_text()
    main()
