"""DIAYN on a reward-free env for S seeds at once: skill-conditioned SAC + a skill discriminator (the UMRL proposal).

The command line is ``recipes/diayn.py`` (``seed=0``, or ``seeds=[0,1,2]`` for several in one program); from Python,
:class:`DIAYNTrainer` (``step``, ``checkpoint``, ``log``, ``train``) on a composed config
(:func:`umrl.trainers.compose`), or ``umrl.trainers.train("diayn", overrides)``.

Seeds as a batch dimension: the S seeds' networks are stacked (:class:`~umrl.objectives.stacked_diayn.StackedDIAYNLoss`,
one batched matmul per layer for all seeds), their env copies are one batched env (``env.num_envs`` copies per seed),
their transitions one replay of rows ``[S]`` (:class:`~umrl.seed_replay.SeedReplay`). Each seed draws everything
random from its own streams (a torch generator: actions, replay indices, action noise, skills at reset; a numpy
generator: MuJoCo's reset noise), and its networks are initialised as a single-seed run initialises them, so seed
``s``'s run sees the same data and takes the same updates whichever seeds share the program, to float rounding
(batched and single kernels may round an element differently: 3e-8 after 80 updates, measured in
``tests/test_diayn_seeds.py``).

Schedule: each :meth:`DIAYNTrainer.step` takes ``collector.frames_per_batch`` env steps per seed (default
``env.num_envs``: one step of each copy), then ``optim.updates_per_frame`` fused updates per new frame: with the
defaults one env step, then one update, as DIAYN's reference code (``sac/algos/base.py``'s loop with
``n_train_repeat=1``). A larger ``collector.frames_per_batch`` (e.g. ``env.num_envs × env.horizon``) is the bulk
collect-then-update schedule. The first ``collector.init_random_frames`` frames take uniform random actions.

Logged (namespaced; with several seeds each seed's under ``seed<s>/``): ``train/`` losses, ``discriminator_accuracy``
(on replay samples), ``pseudo_reward``, ``entropy``, ``episode_return`` (undiscounted pseudo-return of finished
episodes, scored by the discriminator when they are logged); ``eval/`` on fresh rollouts of every skill: ``final_state_accuracy`` (argmax D(z|s_T) == z), spread of the
skills' end points (``end_pairwise_distance``, ``centroid_pairwise_distance``, ``centroid_hull_area`` in 2-D,
``centroid_std``/``range`` for half_cheetah's velocities), ``task_distance_median``/``max``, the same for a uniformly
random policy under ``eval/random_*`` (once); ``time/`` env steps/s and seed-updates/s (all seeds), elapsed seconds.

Files: per seed ``<output_dir>/seed<s>/checkpoints/step_<frames>.safetensors`` (format ``umrl.diayn.v1`` with the seed's
skills: every DIAYN loader, the MAML recipe's ``diayn_checkpoint`` and the suite read it) and
``<output_dir>/seed<s>/figures/``; the program's whole state for ``resume=true`` in
``<output_dir>/checkpoints/step_<frames>.safetensors`` (format ``umrl.diayn_seeds.v1``, :mod:`umrl.checkpoints.diayn`):
networks, Adam states, counters, the replay, every generator, the env's reset noise and the episodes in progress. A
run resumed from any checkpoint, one a SIGTERM or Ctrl-C wrote between scheduled ones included, finishes
bit-identical to an uninterrupted one in every tensor of its checkpoint and every logged training metric.
"""
from __future__ import annotations

import time
import warnings
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.objectives import SoftUpdate

from umrl.checkpoints.diayn import (
    DIAYN_SEEDS_FORMAT,
    save_diayn_checkpoint,
    seed_run_dir,
)
from umrl.checkpoints.folder import Checkpointer
from umrl.checkpoints.format import check_budget_left
from umrl.configs import RESUME_ALLOW, check_resume, validate
from umrl.configs.diayn import DIAYNConfig, resolve_seeds
from umrl.envs import get_env_spec, make_env
from umrl.envs.threads import torch_threads_beside_physics
from umrl.folder_lock import claim_run_folder, releases_folder_on_error
from umrl.loggers import log_image
from umrl.modules.discriminator import make_discriminator
from umrl.modules.sac import make_skill_actor, make_skill_qvalue
from umrl.objectives.diayn import DIAYNLoss
from umrl.objectives.stacked_diayn import StackedDIAYNLoss, StackedDIAYNUpdate, tanh_normal_action
from umrl.resume_state import env_state, keeps_episodes, load_env_state
from umrl.rng import isolated_rng, rng_state, set_rng_state
from umrl.seed_replay import SeedReplay
from umrl.skill_coverage import coverage_metrics, evaluate_skills, plot_coverage
from umrl.trainers.base import Trainer
from umrl.transforms.discriminator_reward import skill_reward
from umrl.transforms.skill import SkillTransform
from umrl.validation import check_not_diverged, resolve_device

__all__ = ["DIAYNTrainer", "evaluate", "make_skill_env", "train"]

TRANSITION_KEYS = ("observation", "skill", "action", ("next", "observation"), ("next", "skill"),
                   ("next", "terminated"))
"""What the replay keeps of each env step (what :class:`StackedDIAYNLoss` reads, its noise aside)."""


def make_skill_env(cfg: DictConfig, num_envs: int, num_skills: int, seed: int, generators=None):
    """The DIAYN env: ``make_env`` + a :class:`SkillTransform` (skills from ``generators``, one per equal group of
    copies, when given)."""
    env = make_env(cfg.env.name, num_envs, seed=seed, device=resolve_device("device", cfg.device),
                   horizon=cfg.env.horizon, backend=cfg.env.backend)
    env.append_transform(SkillTransform(num_skills, generators=generators))
    return env


def seed_reset_noise(env, seeds: list[int]) -> None:
    """Give each seed's group of copies of ``env`` its own reset-noise stream (MuJoCo's batched env: ``seed_copies``;
    point_nav starts deterministically, and the config refuses gymnasium's vector env with several seeds)."""
    if hasattr(env.base_env, "seed_copies"):
        env.base_env.seed_copies(seeds)


def evaluate(cfg, env, actor, discriminator, num_skills, step, figure_path, logger, baseline, seed: int,
             prefix: str = "") -> dict:
    """Fresh rollouts of every skill of one seed: coverage metrics, final-state accuracy, the figure at
    ``figure_path``. The rollouts draw from generators seeded by ``seed`` and the frame count alone (the training's
    generators do not move): a seed's evaluation is the same whichever seeds share the program."""
    env.set_seed(seed + 10_000)
    with isolated_rng():
        torch.manual_seed(seed + step)
        result = evaluate_skills(env, actor, env_name=cfg.env.name, num_skills=num_skills,
                                 episodes_per_skill=cfg.eval.episodes_per_skill, horizon=cfg.env.horizon)
    eval_tasks = get_env_spec(cfg.env.name).eval_tasks()
    metrics = {f"{prefix}eval/{k}": v
               for k, v in coverage_metrics(result, num_skills, discriminator, eval_tasks).items()}
    figure = plot_coverage(result["end_point"], figure_path, eval_tasks=eval_tasks, skills=result["skill"],
                           baseline=baseline["end_point"],
                           title=f"DIAYN {cfg.env.name} seed {seed}, {num_skills} skills, {step} env steps")
    log_image(logger, f"{prefix}eval/skill_coverage", figure, step)
    return metrics


def seed_networks(cfg: DictConfig, seed: int, obs_dim: int, act_dim: int, num_skills: int) -> DIAYNLoss:
    """Seed ``seed``'s actor, twin Q and discriminator, initialised from ``torch.manual_seed(seed)`` in a forked
    generator (the same weights whichever seeds share the program), as a TorchRL-contract :class:`DIAYNLoss`."""
    disc_dims = (None if cfg.network.discriminator_input_dims is None
                 else list(cfg.network.discriminator_input_dims))
    hidden = list(cfg.network.hidden)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        actor = make_skill_actor(obs_dim, num_skills, act_dim, hidden=hidden)
        discriminator = make_discriminator(obs_dim, num_skills, hidden=list(cfg.network.discriminator_hidden),
                                           input_dims=disc_dims)
        qvalue = make_skill_qvalue(obs_dim, num_skills, act_dim, hidden=hidden)
        loss = DIAYNLoss(actor, qvalue, discriminator, num_skills=num_skills, alpha_init=cfg.optim.alpha,
                         fixed_alpha=cfg.optim.fixed_alpha, target_entropy=-float(act_dim))
    SoftUpdate(loss.sac_loss, tau=cfg.optim.tau)  # declares the targets' updater (the stacked update averages them)
    return loss


class DIAYNTrainer(Trainer):
    """DIAYN for ``seeds`` (or ``[seed]``) from a config (checked against :class:`~umrl.configs.diayn.DIAYNConfig`).

    Construction builds every seed's networks (:func:`seed_networks`), stacks them into one loss and update, builds
    the batched training env (``env.num_envs`` copies per seed), the evaluation env and the replay, and with
    ``cfg.resume`` restores the latest program checkpoint (:meth:`load_state_dict`). :meth:`setup` (run by the
    first :meth:`step` or :meth:`train`) rolls out a uniformly random policy (the evaluations' baseline),
    scores it with each seed's initial discriminator (logged once under ``eval/random_*``) and opens the
    logger.

    Construction first locks ``output_dir`` until :meth:`close` (:func:`umrl.folder_lock.claim_run_folder`: a folder
    another run uses, or one holding checkpoints while ``cfg.resume`` is false, is refused before any work).

    :meth:`step` takes ``collector.frames_per_batch`` env steps per seed, then the updates they earn;
    :meth:`evaluate` rolls out every seed's skills; :meth:`save` saves the program (the episodes in progress
    included: they go on; gymnasium's envs, which cannot give them, restart them, as a resumed run does) and each
    seed's skills; :meth:`train` steps to ``collector.total_frames``
    per seed, evaluating every ``eval.every`` frames and at the end (the loop and its hook points are
    :class:`~umrl.trainers.base.Trainer`'s). A config that differs from the checkpoint's beyond
    ``umrl.configs.RESUME_ALLOW`` (on gymnasium's envs also in ``checkpoint.every``) is refused. Nothing
    process-wide is set
    (:mod:`umrl.process`).
    """

    name = "diayn"
    PHASES = ("collect", "update")
    stop_message = "at {progress} of {budget} frames per seed"
    progress_unit = "frames"

    @releases_folder_on_error
    def __init__(self, cfg: DictConfig):
        super().__init__()
        self.cfg = cfg = validate(cfg, DIAYNConfig)
        self.seeds = seeds = resolve_seeds(cfg)
        self.num_skills = num_skills = cfg.num_skills
        self.device = device = torch.device(resolve_device("device", cfg.device))
        self.output_dir = Path(cfg.output_dir)
        self.checkpointer = Checkpointer(self.output_dir / "checkpoints", keep_all=cfg.checkpoint.keep_all)
        self.seed_checkpointers = [Checkpointer(seed_run_dir(self.output_dir, s) / "checkpoints",
                                                keep_all=cfg.checkpoint.keep_all) for s in seeds]
        self.folder_lock = claim_run_folder(self.output_dir, resume=cfg.resume,
                                            checkpointers=[self.checkpointer, *self.seed_checkpointers])
        S, n = len(seeds), cfg.env.num_envs

        env_spec = get_env_spec(cfg.env.name)
        self.obs_dim, self.act_dim = obs_dim, act_dim = env_spec.obs_dim, env_spec.act_dim
        disc_dims = (None if cfg.network.discriminator_input_dims is None
                     else list(cfg.network.discriminator_input_dims))
        self.seed_meta = {"env": cfg.env.name, "obs_dim": obs_dim, "act_dim": act_dim, "num_skills": num_skills,
                          "hidden": list(cfg.network.hidden),
                          "discriminator_hidden": list(cfg.network.discriminator_hidden),
                          "discriminator_observation_key": ["observation"], "discriminator_input_dims": disc_dims}
        self.meta = {**self.seed_meta, "seeds": list(seeds)}
        path, state = (DIAYN_SEEDS_FORMAT.load_for_resume(self.checkpointer, self.meta,
                                                          lambda saved: check_resume(saved, cfg))
                       if cfg.resume else (None, None))
        if state is not None:
            check_budget_left("collector.total_frames", cfg.collector.total_frames,
                              state["counters"]["frames"], "frames", self.output_dir)

        # --- networks, loss, optimisers: each seed's as a single-seed run builds them, then stacked --------
        self.seed_losses = [seed_networks(cfg, s, obs_dim, act_dim, num_skills).to(device) for s in seeds]
        self.loss = StackedDIAYNLoss.from_losses(self.seed_losses, gamma=cfg.optim.gamma).to(device)
        self.update = StackedDIAYNUpdate(self.loss, lr=cfg.optim.lr, discriminator_lr=cfg.optim.discriminator_lr,
                                         tau=cfg.optim.tau, compile=cfg.optim.compile,
                                         cudagraphs=cfg.optim.cudagraphs)
        self.generators = [torch.Generator(device=device).manual_seed(s) for s in seeds]
        self.counters = {"frames": 0, "updates": 0, "next_eval": cfg.eval.every, "next_log": cfg.log_every,
                         "next_checkpoint": cfg.checkpoint.every, "update_credit": 0.0}
        self._interval = self._new_interval()

        # --- data ---------------------------------------------------------------------------------------
        self.env = make_skill_env(cfg, S * n, num_skills, seeds[0], self.generators)
        seed_reset_noise(self.env, seeds)
        self.keeps_episodes = keeps_episodes(self.env)  # else every checkpoint restarts them (gymnasium's envs)
        self.eval_env = make_skill_env(cfg, num_skills * cfg.eval.episodes_per_skill, num_skills, seeds[0] + 10_000)
        self.replay = SeedReplay(cfg.replay_buffer.size, batch_size=cfg.replay_buffer.batch_size,
                                 generators=self.generators, act_dim=act_dim, device=device)
        self.warmup = max(cfg.collector.init_random_frames, cfg.replay_buffer.batch_size)
        self.episode_return = torch.zeros(S * n, device=device)
        # read once: an OmegaConf attribute costs ~50 us, and the loop reads several per env step
        self.settings = {"num_envs": n, "steps": cfg.collector.frames_per_batch // n,
                         "random_frames": cfg.collector.init_random_frames,
                         "updates_per_frame": cfg.optim.updates_per_frame, "total_frames": cfg.collector.total_frames,
                         "log_every": cfg.log_every, "eval_every": cfg.eval.every}

        self.baseline: dict | None = None  # the random policy's rollouts (setup)
        self.random_metrics: dict[str, float] = {}  # their scores by the initial discriminators (setup)
        if state is not None:
            if not self.keeps_episodes:  # the episodes restart at every checkpoint: another schedule, another run
                check_resume(state["config"], cfg, [key for key in RESUME_ALLOW if key != "checkpoint.every"])
            self.restore(path, state)
            every = cfg.checkpoint.every
            if state["config"]["checkpoint"]["every"] != every:  # a changed schedule starts from here
                self.counters["next_checkpoint"] = (self.counters["frames"] // every + 1) * every
        else:
            self._carry = self.env.reset()

    def prefix(self, index: int) -> str:
        """The metric prefix of seed ``seeds[index]``: none for a single seed, ``seed<s>/`` for several."""
        return "" if len(self.seeds) == 1 else f"seed{self.seeds[index]}/"

    @property
    def progress(self) -> int:
        """Env frames per seed so far."""
        return self.counters["frames"]

    @property
    def budget(self) -> int:
        return self.settings["total_frames"]

    def _setup(self) -> dict[str, float]:
        """The uniformly random policy's rollouts of every skill (the evaluations' baseline, drawn from the
        seeds' own streams: the training's do not move) and, unless a run's state holds them, their scores by
        each seed's initial discriminator (returned, to be logged once)."""
        cfg, seed = self.cfg, self.seeds[0]
        self.eval_env.set_seed(seed + 10_000)
        with isolated_rng():
            torch.manual_seed(seed)
            self.baseline = evaluate_skills(self.eval_env, None, env_name=cfg.env.name,
                                            num_skills=self.num_skills,
                                            episodes_per_skill=cfg.eval.episodes_per_skill,
                                            horizon=cfg.env.horizon)
        if self.random_metrics:
            return {}
        eval_tasks = get_env_spec(cfg.env.name).eval_tasks()
        for i, loss in enumerate(self.seed_losses):
            scores = coverage_metrics(self.baseline, self.num_skills, loss.discriminator, eval_tasks)
            self.random_metrics.update({f"{self.prefix(i)}eval/random_{k}": v for k, v in scores.items()})
        return self.random_metrics

    def _evaluation_due(self) -> bool:
        """Every ``eval.every`` frames."""
        due = self.counters["frames"] >= self.counters["next_eval"]
        self.counters["next_eval"] += self.settings["eval_every"] * due
        return due

    def _checkpoint_due(self, before: int) -> bool:
        """Every ``checkpoint.every`` frames (a schedule the counters keep: a resumed run continues it)."""
        due = self.counters["frames"] >= self.counters["next_checkpoint"]
        self.counters["next_checkpoint"] += self.cfg.checkpoint.every * due
        return due

    def state_dict(self) -> dict:
        """Stacked networks, Adam states, counters, the random policy's metrics, the replay, every generator (the
        global ones and each seed's), the training env's state (reset noise and its copies' physics) and, where
        the env gives its physics (not gymnasium's), the episodes in progress (``"episodes"``: the env's last output
        ``"carry"`` ``[S * n]``, with each copy's step count and skill; ``"episode_return"`` ``[S * n]``, the
        scored part of each unfinished episode; ``"interval"``, what the next logged training metrics cover: its
        env steps still to be scored, the summed losses, counts and times)."""
        return {"loss": self.loss.state_dict(),
                "optimizers": {name: opt.state_dict() for name, opt in self.update.optimizers.items()},
                "counters": dict(self.counters), "random_metrics": dict(self.random_metrics),
                "replay": self.replay.state_dict(), "rng": rng_state(**self._named_generators()),
                "envs": {"train": env_state(self.env, episodes=True)},
                **({"episodes": {"carry": self._carry.clone(), "episode_return": self.episode_return.clone(),
                                 "interval": {**self._interval, "episodes": self._pending_steps(),
                                              "returns": list(self._interval["returns"])}}}
                   if self.keeps_episodes else {})}

    def _pending_steps(self) -> list[TensorDictBase]:
        """The interval's steps still to be scored as one batch ``[T, S * n]`` (a list of it, empty if none):
        what :meth:`_flush_episodes` scores, in one tensor per key rather than one per step."""
        steps = self._interval["episodes"]
        return [torch.cat(steps)] if steps else []

    def _named_generators(self) -> dict[str, torch.Generator]:
        return {f"seed{s}": g for s, g in zip(self.seeds, self.generators)}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`'s (or a program checkpoint's) state: the episodes in progress go on where
        they stood (``ValueError`` if they do not fit this run's env). On gymnasium's envs they restart, as after
        every checkpoint there; a checkpoint written before umrl kept them restarts them with a warning."""
        template = self.env.reset()  # the carry's keys and shapes; what this reset drew is restored below
        self.loss.load_state_dict(state["loss"])
        for name, optimizer in self.update.optimizers.items():
            optimizer.load_state_dict(state["optimizers"][name])
        self.counters.update(state["counters"])
        self.random_metrics = dict(state["random_metrics"])
        self.replay.load_state_dict(state["replay"])
        env_episodes = load_env_state(self.env, state["envs"]["train"])
        set_rng_state(state["rng"], **self._named_generators())
        if env_episodes and state.get("episodes") is not None:
            self._load_episodes(state["episodes"], template)
            return
        if self.keeps_episodes:
            warnings.warn(f"the DIAYN state at {self.counters['frames']} frames holds no episodes in progress (saved "
                          "before umrl kept them): they restart here, so the run departs from an uninterrupted one",
                          stacklevel=2)
        self._interval = self._new_interval()
        self._restart_episodes()

    def _restart_episodes(self) -> None:
        """Every copy's episode starts anew (where the env cannot give its episodes in progress to a checkpoint)."""
        self._carry = self.env.reset()
        self.episode_return.zero_()

    def _load_episodes(self, episodes: dict, template: TensorDictBase) -> None:
        """Restore :meth:`state_dict`'s ``"episodes"``, checked against ``template`` (a reset's output)."""
        carry, returns, interval = episodes["carry"], episodes["episode_return"], episodes["interval"]

        def layout(value: torch.Tensor) -> str:
            return f"{list(value.shape)} {str(value.dtype).removeprefix('torch.')}"

        expected = {key: layout(value) for key, value in template.items(True, True)}
        held = carry.keys(True, True) if isinstance(carry, TensorDictBase) else ()
        found = {key: layout(carry[key]) if key in held else None for key in expected}
        if found != expected:
            saved = {key: found[key] for key in expected if found[key] != expected[key]}
            wanted = {key: expected[key] for key in saved}
            raise ValueError(f"the saved episodes in progress do not fit this run's env: carry entries {saved} "
                             f"where it has {wanted}.")
        shape = list(returns.shape) if isinstance(returns, torch.Tensor) else type(returns).__name__
        entries = sorted(interval) if isinstance(interval, dict) else type(interval).__name__
        if shape != list(self.episode_return.shape) or entries != sorted(self._new_interval()):
            raise ValueError(f"the saved episodes in progress do not fit this run: episode_return {shape} (expected "
                             f"{list(self.episode_return.shape)}), interval entries {entries} (expected "
                             f"{sorted(self._new_interval())}).")
        device = self.device
        self._carry = carry.select(*expected).to(device).clone()  # its last action, overwritten first, aside
        self.episode_return = returns.to(device).clone()
        self._interval = {**interval, "sums": None if interval["sums"] is None else interval["sums"].to(device),
                          "episodes": [steps.to(device) for steps in interval["episodes"]],
                          "returns": [ended.to(device) for ended in interval["returns"]]}

    def _save(self) -> Path:
        """The program's state and each seed's skills; the episodes go on (on gymnasium's envs they restart, as a
        run resumed from here restarts them: the episodes cut here are not counted)."""
        frames = self.counters["frames"]
        path = DIAYN_SEEDS_FORMAT.save(self.checkpointer, frames, self.meta, self.cfg, **self.state_dict())
        for i, seed in enumerate(self.seeds):
            self.loss.copy_to(i, self.seed_losses[i])
            seed_cfg = OmegaConf.merge(self.cfg, {"seed": seed, "seeds": [seed],
                                                  "output_dir": str(seed_run_dir(self.output_dir, seed))})
            save_diayn_checkpoint(self.seed_checkpointers[i], meta=self.seed_meta,
                                  actor=self.seed_losses[i].sac_loss.actor_network,
                                  discriminator=self.seed_losses[i].discriminator, counters=self.counters,
                                  config=seed_cfg)
        if not self.keeps_episodes:
            self._flush_episodes()
            self._restart_episodes()
        return path

    def _evaluate(self, final: bool) -> dict[str, float]:
        """Fresh rollouts of every seed's skills (:func:`evaluate`), figures at
        ``<output_dir>/seed<s>/figures/skill_coverage_<frames>.png`` (``skill_coverage.png`` for the final
        one)."""
        name = "skill_coverage.png" if final else f"skill_coverage_{self.counters['frames']}.png"
        metrics = {}
        for i, seed in enumerate(self.seeds):
            self.loss.copy_to(i, self.seed_losses[i])
            loss = self.seed_losses[i]
            metrics.update(evaluate(self.cfg, self.eval_env, loss.sac_loss.actor_network, loss.discriminator,
                                    self.num_skills, self.counters["frames"],
                                    seed_run_dir(self.output_dir, seed) / "figures" / name, self.logger,
                                    self.baseline, seed, self.prefix(i)))
        return metrics

    @torch.no_grad()
    def _act(self, carry) -> torch.Tensor:
        """Actions ``[S * n, act]`` for the env's current state: uniform during the warm-up, else each seed's policy
        with noise from its generator."""
        S, n = len(self.seeds), self.settings["num_envs"]
        if self.counters["frames"] < self.settings["random_frames"]:
            return self.replay.draw((n, self.act_dim), "uniform").view(S * n, -1)
        params = self.loss.actor(torch.cat([carry["observation"], carry["skill"]], -1).view(S, n, -1))
        noise = self.replay.draw((n, self.act_dim), "normal")
        return tanh_normal_action(*self.loss.scale_map(params), noise).reshape(S * n, -1)

    def _collect(self, steps: int) -> TensorDictBase:
        """``steps`` env steps of every copy: transitions ``[steps * n, S]`` (their states, skills and ends also kept
        for the logged episode returns)."""
        S, n = len(self.seeds), self.settings["num_envs"]
        carry, transitions = self._carry, []
        with torch_threads_beside_physics(self.env):
            for _ in range(steps):
                carry.set("action", self._act(carry))
                out, carry = self.env.step_and_maybe_reset(carry)
                transitions.append(out.select(*TRANSITION_KEYS, ("next", "done")))
        self._carry = carry
        data = transitions[0].unsqueeze(0) if steps == 1 else torch.stack(transitions)  # [steps, S * n]
        self._interval["episodes"].append(data.select("observation", "skill", ("next", "done")))
        if n > 1:
            data = data.view(steps, S, n).transpose(1, 2)
        return data.reshape(steps * n, S).exclude(("next", "done"))

    @torch.no_grad()
    def _flush_episodes(self) -> None:
        """Score the interval's pending steps (batches of ``[T, S * n]``) by the current discriminators in one call
        and keep the pseudo-returns of the episodes that ended in them (``[S, T * n]``, NaN where none ended);
        unfinished episodes carry over in :attr:`episode_return`."""
        steps = self._interval["episodes"]
        if not steps:
            return
        self._interval["episodes"] = []
        S, n = len(self.seeds), self.settings["num_envs"]
        data = torch.cat(steps)  # [T, S * n]
        T = data.shape[0]
        observation = data["observation"].view(T, S, n, -1).permute(1, 0, 2, 3).reshape(S, T * n, -1)
        skill = data["skill"].view(T, S, n, -1).permute(1, 0, 2, 3).reshape(S, T * n, -1)
        rewards = skill_reward(self.loss.discriminator_logits(observation), skill)
        rewards = rewards.view(S, T, n).permute(1, 0, 2).reshape(T, S * n)
        done = data["next", "done"].view(T, S * n)
        # running totals since the carried-over episode start; an episode ending at t returns its total minus the
        # total at the previous end of the same copy (0 before the first)
        total = torch.cat([torch.zeros_like(rewards[:1]), self.episode_return + rewards.cumsum(0)])  # [T + 1, C]
        steps = torch.arange(1, T + 1, device=done.device).unsqueeze(-1)
        last_end = torch.where(done, steps, 0).cummax(0).values  # [T, C]: row of total at the latest end up to t
        previous_end = torch.cat([torch.zeros_like(last_end[:1]), last_end[:-1]])
        returns = torch.where(done, total[1:] - total.gather(0, previous_end), torch.nan)  # [T, C]
        self.episode_return = total[-1] - total.gather(0, last_end[-1:]).squeeze(0)
        self._interval["returns"].append(returns.view(T, S, n).transpose(0, 1).reshape(S, T * n))

    def _step(self) -> dict[str, float]:
        """One batch: ``collector.frames_per_batch`` env steps per seed into the replay, the updates they
        earn. Returns the metrics due at this frame count: the training metrics averaged since the last ones
        (every ``log_every`` frames); an empty dict between them."""
        counters, settings = self.counters, self.settings
        collect_start = time.perf_counter()
        with self.phase("collect"):
            data = self._collect(settings["steps"])
            self.replay.extend(data)
        self._interval["collect_s"] += time.perf_counter() - collect_start
        counters["frames"] += data.shape[0]
        self._interval["frames"] += data.shape[0]

        if len(self.replay) >= self.warmup:
            update_start = time.perf_counter()
            counters["update_credit"] += data.shape[0] * settings["updates_per_frame"]
            with self.phase("update"):
                for _ in range(int(counters["update_credit"])):
                    out = self.update(self.replay.sample())
                    self._interval["sums"] = out if self._interval["sums"] is None else self._interval["sums"] + out
                    self._interval["updates"] += 1
            counters["updates"] += int(counters["update_credit"])
            counters["update_credit"] -= int(counters["update_credit"])
            self._interval["update_s"] += time.perf_counter() - update_start
        metrics = {}
        if counters["frames"] >= counters["next_log"] or self.done:
            metrics = self._interval_metrics()
            counters["next_log"] = (counters["frames"] // settings["log_every"] + 1) * settings["log_every"]
        return metrics

    def _new_interval(self) -> dict:
        return {"frames": 0, "updates": 0, "collect_s": 0.0, "update_s": 0.0, "sums": None, "episodes": [],
                "returns": []}

    def _interval_metrics(self) -> dict[str, float]:
        """The training metrics since the last call (means over its updates and finished episodes; the losses are
        checked finite here, once per interval: a per-update check would wait on a GPU after every update)."""
        self._flush_episodes()
        interval, counters, seeds = self._interval, self.counters, self.seeds
        self._interval = self._new_interval()
        metrics = {"time/env_steps_per_s": interval["frames"] * len(seeds) / max(interval["collect_s"], 1e-9),
                   "time/elapsed_s": time.perf_counter() - self.start_time, "train/frames": counters["frames"],
                   "train/updates": counters["updates"]}
        if interval["updates"]:
            mean = interval["sums"] / interval["updates"]  # [S]
            first = counters["updates"] - interval["updates"]
            check_not_diverged({k: v for k, v in mean.items() if k.startswith("loss_")},
                               f"DIAYN updates {first}..{counters['updates'] - 1}")
            metrics["time/seed_updates_per_s"] = interval["updates"] * len(seeds) / max(interval["update_s"], 1e-9)
            for i in range(len(seeds)):
                metrics.update({f"{self.prefix(i)}train/{k}": float(v[i]) for k, v in mean.items()})
        if interval["returns"]:
            returns = torch.cat(interval["returns"], dim=1)
            for i in range(len(seeds)):
                ended = returns[i][~returns[i].isnan()]
                if ended.numel():
                    metrics[f"{self.prefix(i)}train/episode_return"] = float(ended.mean())
        return metrics

    def _result(self) -> dict:
        """The random policy's metrics and each seed's run folder (``runs``)."""
        return {**self.random_metrics, "runs": [str(seed_run_dir(self.output_dir, s)) for s in self.seeds]}

    def _description(self) -> str:
        return f"DIAYN {self.cfg.env.name} seeds {list(self.seeds)}"

    def _envs(self) -> list:
        return [self.env, self.eval_env]


def train(cfg: DictConfig) -> dict:
    """Run DIAYN as configured in this process (:class:`DIAYNTrainer`, then closed): the last logged metrics (also
    the final evaluation's), the program checkpoint path and the seeds' run folders."""
    trainer = DIAYNTrainer(cfg)
    try:
        return trainer.train()
    finally:
        trainer.close()
