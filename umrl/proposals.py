"""Task proposals for meta-training: where MAML's tasks come from.

A proposal owns a batched env of ``T × N`` copies (task-major: copy ``t * N + n`` runs task ``t``) whose
``("next", "reward")`` is the task reward, and chooses the ``T`` tasks of each meta-iteration (:meth:`resample`):

* ``oracle`` — the hand-designed task family (:func:`umrl.envs.get_task_family`, rewards by
  :class:`~umrl.envs.TaskReward`); fresh tasks every meta-iteration.
* ``diayn`` — UML-DIAYN: the task is a DIAYN skill z with reward ``log D(z|s') − log p(z)`` from a trained
  discriminator (``umrl.checkpoints.load_discriminator``); the meta-batch is every skill (or a random subset
  of ``num_tasks`` skills each meta-iteration if fewer tasks are asked for).
* ``random`` — UML-random: the same reward from a seeded, randomly initialised, frozen discriminator.
* ``random_arena`` — an **ablation, not the paper's method** (display "UML-random (bounded arena, ablation)"):
  ``random`` meta-trained with point_nav's position clipped to [-a, a]² (``arena``, default :data:`RANDOM_ARENA`).
  A ReLU discriminator with zero biases is positively homogeneous, so each random task is "go as far as possible
  in direction z"; in the arena every task's best reachable point lies within ~a of the evaluation goals. The
  meta-test env is never bounded.

Any proposal takes ``arena`` (the env option of :class:`~umrl.envs.point_nav.PointNavEnv`) for meta-training.

Skills are pinned per env copy with :meth:`~umrl.transforms.skill.SkillTransform.pin` (the policy never sees them:
it must infer its task from rewards), so ``"skill"`` ``[B, K]`` appears in rollouts for inspection only.

Example:
    >>> from umrl.modules.policy import make_gaussian_policy
    >>> from umrl.rollout import collect
    >>> proposal = make_proposal("oracle", "point_nav", num_tasks=20, trajectories_per_task=4, seed=0, horizon=10)
    >>> tasks = proposal.resample(torch.Generator().manual_seed(0))   # [20, 2] goals
    >>> batch = collect(proposal.env, make_gaussian_policy(2, 2, hidden=[16]), num_tasks=20, horizon=10)
    >>> batch.batch_size                                              # [tasks, trajectories, steps]
    torch.Size([20, 4, 10])
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import torch
from torchrl.envs import TransformedEnv

from umrl.envs import TaskReward, get_env_spec, make_env, make_task_env
from umrl.envs.registry import check_observation_size
from umrl.modules.discriminator import make_discriminator
from umrl.transforms.discriminator_reward import DiscriminatorReward
from umrl.transforms.skill import SkillTransform
from umrl.validation import InvalidValue, check_device

PROPOSALS = ("diayn", "random", "oracle", "random_arena")
RANDOM_ARENA = 1.0
"""Half-width of the ``random_arena`` ablation's arena when ``arena`` is not given."""

__all__ = ["PROPOSALS", "RANDOM_ARENA", "TaskProposal", "make_proposal"]


@dataclass
class TaskProposal:
    """A meta-training task source.

    Attributes:
        name: one of :data:`PROPOSALS`.
        env: batched env with ``batch_size == [num_tasks * trajectories_per_task]``.
        num_tasks: ``T``, tasks per meta-iteration.
        trajectories_per_task: ``N``.
        num_skills: ``K`` for skill proposals, ``None`` for oracle.
        task_reward: the env's :class:`~umrl.envs.TaskReward` (oracle) that :meth:`resample` gives new tasks.
        skills: the env's :class:`~umrl.transforms.skill.SkillTransform` (diayn, random) that :meth:`resample` pins.
    """

    name: str
    env: TransformedEnv
    num_tasks: int
    trajectories_per_task: int
    num_skills: int | None = None
    task_reward: TaskReward | None = None
    skills: SkillTransform | None = None

    def resample(self, generator: torch.Generator | None = None) -> torch.Tensor:
        """Choose the next meta-batch and assign it to the env copies (effective from the next reset).

        Returns the tasks: goal/velocity parameters ``[T, task_dim]`` (oracle) or skill indices ``[T]`` (int64).
        """
        n = self.trajectories_per_task
        if self.task_reward is not None:
            tasks = self.task_reward.family.sample(self.num_tasks, generator)
            self.task_reward.set_tasks(tasks.repeat_interleave(n, 0))
            return tasks
        if self.num_tasks == self.num_skills:
            skills = torch.arange(self.num_skills)
        else:
            skills = torch.randperm(self.num_skills, generator=generator)[: self.num_tasks]
        self.skills.pin(skills.repeat_interleave(n, 0))
        return skills


def _skill_env(env_name: str, discriminator, num_skills: int, batch: int, seed: int, horizon: int,
               device: torch.device, options: dict) -> tuple[TransformedEnv, SkillTransform]:
    env = make_env(env_name, batch, seed=seed, horizon=horizon, device=device, **options)
    skills = SkillTransform(num_skills)
    env.append_transform(skills)
    # a proposed task rewards the state its action led to, as the hand-designed task rewards do
    env.append_transform(DiscriminatorReward(discriminator, num_skills, observation_key=("next", "observation")))
    return env, skills


def make_proposal(
    name: str,
    env_name: str,
    *,
    num_tasks: int | None = None,
    trajectories_per_task: int = 40,
    seed: int = 0,
    horizon: int = 100,
    num_skills: int | None = None,
    diayn_checkpoint: str | os.PathLike | None = None,
    discriminator_hidden: tuple[int, ...] | None = None,
    device: torch.device | str = "cpu",
    arena: float | None = None,
) -> TaskProposal:
    """Build a :class:`TaskProposal`.

    Args:
        name: one of :data:`PROPOSALS`.
        env_name: a registered env (:data:`umrl.envs.ENV_NAMES`).

    Keyword Args:
        num_tasks: meta-batch ``T``; ``None``: the number of skills (diayn/random); the oracle needs it (the
            recipe's ``meta_batch_size``, null: its ``default_num_skills``, docs/protocol.md's 50/20/20).
        trajectories_per_task: ``N`` env copies per task.
        seed: seeds the env and the random discriminator's weights.
        horizon: episode length.
        num_skills: ``K`` of the random discriminator (random proposals need it; the recipe's ``num_skills``, null:
            its ``default_num_skills``); diayn reads it from the checkpoint.
        diayn_checkpoint: DIAYN run directory or ``step_*.safetensors`` file (proposal ``diayn`` only).
        discriminator_hidden: widths of the random discriminator (random proposals need them; the recipe's
            ``discriminator_hidden``: DIAYN's discriminator, left at its random initialisation).
        device: device of the env's tensors and of the discriminator (MuJoCo physics stays on CPU threads, its
            outputs move once per step); tasks are drawn on the CPU (the same tasks on every device).
        arena: clip point_nav's position to [-arena, arena]² (> 0); ``None``: unbounded, or :data:`RANDOM_ARENA`
            for ``random_arena``. Other envs refuse it.
    """
    if name not in PROPOSALS:
        raise ValueError(f"unknown proposal {name!r}; valid choices: {list(PROPOSALS)}.")
    if trajectories_per_task < 1 or (num_tasks is not None and num_tasks < 1):
        raise ValueError(f"need num_tasks >= 1 and trajectories_per_task >= 1, got {num_tasks} and {trajectories_per_task}.")
    random = name in ("random", "random_arena")
    if (num_skills is not None or random) and (isinstance(num_skills, bool) or not isinstance(num_skills, int)
                                                or num_skills < 1):
        raise InvalidValue("num_skills", num_skills, f"an integer >= 1 with proposal {name}" if random
                           else "None (the checkpoint's skill count) or an integer >= 1")
    if random and not discriminator_hidden:
        raise InvalidValue("discriminator_hidden", discriminator_hidden,
                           f"the random discriminator's widths with proposal {name}, e.g. (32, 32)")
    if name == "oracle" and num_tasks is None:
        raise InvalidValue("num_tasks", num_tasks, "the meta-batch (an integer >= 1) with proposal oracle")
    device = check_device("device", device)
    n = trajectories_per_task
    spec = get_env_spec(env_name)
    if name == "random_arena" and arena is None:
        arena = RANDOM_ARENA
    options = {} if arena is None else {"arena": arena}
    if name == "oracle":
        tasks = spec.task_family.sample(num_tasks, torch.Generator().manual_seed(seed))
        env = make_task_env(env_name, tasks.repeat_interleave(n, 0), seed=seed, horizon=horizon, device=device,
                            **options)
        return TaskProposal(name, env, num_tasks, n, task_reward=env.transform[-1])
    if name == "diayn":
        if diayn_checkpoint is None:
            raise ValueError("proposal=diayn needs diayn_checkpoint=<DIAYN run dir or step_*.safetensors file>.")
        from umrl.checkpoints import load_discriminator

        discriminator, num_skills, trained_obs_dim = load_discriminator(diayn_checkpoint)
        # the checkpoint's env observation, not D's input width (chosen dims)
        check_observation_size(env_name, trained_obs_dim, f"the discriminator of {diayn_checkpoint}")
    else:
        discriminator = make_discriminator(spec.obs_dim, num_skills, hidden=list(discriminator_hidden), seed=seed)
        discriminator = discriminator.eval().requires_grad_(False)
    discriminator = discriminator.to(device)
    num_tasks = num_tasks or num_skills
    if num_tasks > num_skills:
        raise ValueError(f"num_tasks={num_tasks} exceeds the {num_skills} skills: one skill per task.")
    env, skills = _skill_env(env_name, discriminator, num_skills, num_tasks * n, seed, horizon, device, options)
    return TaskProposal(name, env, num_tasks, n, num_skills=num_skills, skills=skills)
