"""Schema of ``umrl/configs/diayn.yaml`` (DIAYN task proposal)."""
# ruff: noqa: RUF009  (the field helpers of umrl.configs.validate return dataclasses.field(...) objects)
from __future__ import annotations

from dataclasses import dataclass

from umrl.configs.common import (
    BatchedEnvConfig,
    CheckpointConfig,
    RunConfig,
    cudagraphs_errors,
)
from umrl.configs.memory import Allocation, allocation_errors, step_bytes
from umrl.configs.validate import boolean, group, int_list, integer, number
from umrl.envs import get_env_spec
from umrl.envs.mujoco import MUJOCO_ENV_NAMES
from umrl.validation import SEED_MAX, InvalidValue


def resolve_seeds(cfg) -> list[int]:
    """The seeds a DIAYN run trains: ``seeds``, or ``[seed]`` when it is null."""
    return list(cfg["seeds"]) if cfg["seeds"] is not None else [cfg["seed"]]


@dataclass
class NetworkConfig:
    """Hidden widths of the actor and each Q-network (``hidden``) and of the discriminator (the env's defaults:
    ``umrl/configs/diayn_env/<env>.yaml``); ``discriminator_input_dims``: null (the whole observation) or the
    observation dims the discriminator sees."""

    hidden: list[int] = int_list(min=1, min_len=1)
    discriminator_hidden: list[int] = int_list(min=1, min_len=1)
    discriminator_input_dims: list[int] | None = int_list(min=0, min_len=1, unique=True)


@dataclass
class CollectorConfig:
    """Per seed: ``total_frames``, ``frames_per_batch`` between update rounds and ``init_random_frames``."""

    total_frames: int = integer(min=1)
    frames_per_batch: int = integer(min=1)
    init_random_frames: int = integer(min=0)


@dataclass
class ReplayBufferConfig:
    size: int = integer(min=1)
    batch_size: int = integer(min=1)


@dataclass
class OptimConfig:
    """SAC's and the discriminator's optimisation; ``alpha`` > 0 (the entropy scale, learnt as its log unless
    ``fixed_alpha``); ``cudagraphs`` only with ``device=cuda``."""

    lr: float = number(gt=0)
    discriminator_lr: float = number(gt=0)
    updates_per_frame: float = number(gt=0)
    gamma: float = number(ge=0, le=1)
    tau: float = number(gt=0, le=1)
    alpha: float = number(gt=0)
    fixed_alpha: bool = boolean()
    compile: bool = boolean()
    cudagraphs: bool = boolean()


@dataclass
class EvalConfig:
    every: int = integer(min=1)
    episodes_per_skill: int = integer(min=1)


@dataclass
class DIAYNConfig(RunConfig):
    """Every key of ``umrl/configs/diayn.yaml`` (:class:`RunConfig`'s and these); the yaml's comments say what each does."""

    seeds: list[int] | None = int_list(min=0, max=SEED_MAX, min_len=1, unique=True)
    log_every: int = integer(min=1)
    env: BatchedEnvConfig = group(BatchedEnvConfig)
    num_skills: int = integer(min=2)
    network: NetworkConfig = group(NetworkConfig)
    collector: CollectorConfig = group(CollectorConfig)
    replay_buffer: ReplayBufferConfig = group(ReplayBufferConfig)
    optim: OptimConfig = group(OptimConfig)
    eval: EvalConfig = group(EvalConfig)
    checkpoint: CheckpointConfig = group(CheckpointConfig)

    @staticmethod
    def cross_check(cfg: dict) -> list[str]:
        """Several seeds run on the batched MuJoCo env (not gymnasium's); the collector's batch holds whole env steps; the replay batch fits in the buffer; the discriminator's input
        dims exist in the env's observation; CUDA graphs run on a CUDA device (``device`` is
        resolved here); the replay buffer and the collector's batch fit in its memory (:func:`memory_errors`)."""
        errors = cudagraphs_errors(cfg["optim"]["cudagraphs"], cfg["device"], "optim.cudagraphs")
        errors += memory_errors(cfg)
        dims, obs_dim = cfg["network"]["discriminator_input_dims"], get_env_spec(cfg["env"]["name"]).obs_dim
        if dims is not None and max(dims) >= obs_dim:
            errors.append(InvalidValue("network.discriminator_input_dims", dims,
                                       f"null or distinct integers < {obs_dim} ({cfg['env']['name']}'s obs_dim)").message())
        seeds, env = resolve_seeds(cfg), cfg["env"]
        if len(seeds) > 1 and env["backend"] == "gym" and env["name"] in MUJOCO_ENV_NAMES:
            errors.append(InvalidValue("env.backend", "gym", "default or batched with several seeds (the batched MuJoCo "
                                       "env gives each seed its own reset noise)",
                                       note=f"seeds={seeds} share gymnasium's vector env").message())
        if len(seeds) > 1 and env["name"].startswith("gym:"):
            errors.append(InvalidValue("seeds", seeds, f"null or one seed with env.name={env['name']} (one program "
                                       "trains several seeds on the batched MuJoCo env only)",
                                       note="the seeds would share one gymnasium vector env's reset noise").message())
        fpb, num_envs = cfg["collector"]["frames_per_batch"], cfg["env"]["num_envs"]
        if fpb % num_envs:
            errors.append(InvalidValue("collector.frames_per_batch", fpb,
                                       f"a multiple of env.num_envs ({num_envs})").message())
        batch, size = cfg["replay_buffer"]["batch_size"], cfg["replay_buffer"]["size"]
        if batch > size:
            errors.append(InvalidValue("replay_buffer.batch_size", batch,
                                       f"an integer <= replay_buffer.size ({size})").message())
        collector, per_frame = cfg["collector"], cfg["optim"]["updates_per_frame"]
        warmup = max(collector["init_random_frames"], batch)  # the recipe's first update waits for both
        if collector["init_random_frames"] >= collector["total_frames"]:
            errors.append(InvalidValue("collector.init_random_frames", collector["init_random_frames"],
                                       f"an integer < collector.total_frames ({collector['total_frames']})",
                                       note="no update would run").message())
        elif batch > collector["total_frames"]:
            errors.append(InvalidValue("replay_buffer.batch_size", batch,
                                       f"an integer <= collector.total_frames ({collector['total_frames']})",
                                       note="no update would run").message())
        elif (collector["total_frames"] - warmup + fpb) * per_frame < 1:  # the batch that fills the warm-up updates
            errors.append(InvalidValue("optim.updates_per_frame", per_frame,
                                       f"a rate giving at least one update in the {collector['total_frames']} frames "
                                       f"after the {warmup}-frame warm-up", note="no update would run").message())
        return errors

    @staticmethod
    def notices(cfg: dict) -> list[str]:
        """A ``collector.total_frames`` that is not a whole number of collector batches: TorchRL's collector rounds it
        up."""
        total, batch = cfg["collector"]["total_frames"], cfg["collector"]["frames_per_batch"]
        runs = -(-total // batch) * batch
        if runs == total:
            return []
        return [InvalidValue("collector.total_frames", total, f"a multiple of collector.frames_per_batch ({batch}) to "
                             "run exactly that many frames",
                             note=f"the collector runs whole batches: {runs} frames will run").message()]


def memory_errors(cfg: dict) -> list[str]:
    """``replay_buffer.size`` and ``collector.frames_per_batch`` transitions of every seed (observations, skill
    one-hots and action, before and after each step) against the memory of ``device`` (:mod:`umrl.configs.memory`)."""
    name, num_skills = cfg["env"]["name"], cfg["num_skills"]
    num_seeds = len(cfg["seeds"] or [cfg["seed"]])
    transition = num_seeds * step_bytes(name, extra_floats=2 * num_skills)
    given = f"with env.name={name}, {num_skills} skills and {num_seeds} seed(s)"
    return allocation_errors([
        Allocation("replay_buffer.size", cfg["replay_buffer"]["size"], transition, "replay buffer", given),
        Allocation("collector.frames_per_batch", cfg["collector"]["frames_per_batch"], transition, "collector batch",
                   given),
    ], cfg["device"])
