"""Where do skills and policies go? Skill end points and discriminator accuracy (DIAYN), visited-state coverage
(VIME), and one coverage figure for both. The coordinates are each env's ``coverage_key`` (its
:class:`~umrl.envs.EnvSpec`).

:func:`evaluate_skills` rolls out every skill ``episodes_per_skill`` times (skills pinned with
:meth:`~umrl.transforms.skill.SkillTransform.pin`) and reads, per rollout, the *final* state (the first step whose
``("next", "done")`` is set):

- ``"end_point"`` [N, d]: the env's coverage coordinates: final x-y (point_nav ``"position"``, ant
  ``"xy_position"``), or for half_cheetah the episode's mean forward velocity ``"x_velocity"`` (d = 1);
- ``"final_observation"`` [N, obs_dim]: what the discriminator sees at the end of the episode.

:func:`coverage_metrics` turns them into scalars (discriminator accuracy on final states; mean pairwise distance of
all end points and of the per-skill centroids; convex-hull area of the centroids in 2-D, their std / range in 1-D).
:func:`state_coverage` / :func:`cumulative_coverage` count the grid cells (2-D) or the velocity range (1-D) of the
states a batch of trajectories visited. :func:`plot_coverage` draws the paper's Figure 5 analogue (skill end points,
or any visited points) with the held-out evaluation tasks overlaid.
"""
from __future__ import annotations

import os
from collections.abc import Callable

import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

from umrl.envs import get_env_spec
from umrl.envs.threads import torch_threads_beside_physics
from umrl.figures import save_figure
from umrl.modules.discriminator import discriminator_logits

__all__ = [
    "convex_hull_area",
    "coverage_metrics",
    "cumulative_coverage",
    "evaluate_skills",
    "final_states",
    "plot_coverage",
    "skill_centroids",
    "state_coverage",
    "visited_states",
]


def final_states(rollout: TensorDictBase, env_name: str) -> TensorDict:
    """Per-rollout final observation and coverage point from a rollout [N, T] (time last in the batch dims).

    The episode ends at the first ``("next", "done")``; the rollout must contain one for each copy (run it for the
    env's horizon).
    """
    done = rollout.get(("next", "done")).squeeze(-1)  # [N, T]
    if not done.any(-1).all():
        raise ValueError("every rollout must contain a done step: roll out for at least the env's horizon.")
    last = done.float().argmax(-1)  # first done
    index = torch.arange(done.shape[0], device=done.device)
    spec = get_env_spec(env_name)
    values = rollout.get(("next", spec.coverage_key))  # [N, T, d]
    if spec.coverage_reduction == "last":
        end_point = values[index, last]
    else:
        alive = (torch.arange(done.shape[1], device=done.device)[None] <= last[:, None]).unsqueeze(-1)
        end_point = (values * alive).sum(1) / alive.sum(1)
    return TensorDict(
        {"end_point": end_point, "final_observation": rollout.get(("next", "observation"))[index, last]},
        batch_size=[done.shape[0]],
    )


def evaluate_skills(
    env: EnvBase,
    policy: Callable | None,
    *,
    env_name: str,
    num_skills: int,
    episodes_per_skill: int,
    horizon: int,
    exploration: ExplorationType = ExplorationType.RANDOM,
) -> TensorDict:
    """Roll out skill ``i % num_skills`` in env copy ``i`` for ``horizon`` steps; returns :func:`final_states` plus
    ``"skill"`` [N] (LongTensor).

    ``env`` must have ``num_skills * episodes_per_skill`` copies and a :class:`~umrl.transforms.skill.SkillTransform`;
    ``policy=None`` takes uniformly random actions (the random-policy baseline). The pin is removed afterwards.
    """
    from umrl.transforms.skill import SkillTransform

    transforms = getattr(env.transform, "transforms", [env.transform])
    skill_transforms = [t for t in transforms if isinstance(t, SkillTransform)]
    if not skill_transforms:
        raise ValueError("evaluate_skills needs an env with a SkillTransform.")
    if env.batch_size != (num_skills * episodes_per_skill,):
        raise ValueError(
            f"the env has batch {tuple(env.batch_size)}; expected ({num_skills * episodes_per_skill},) = "
            "num_skills * episodes_per_skill copies."
        )
    skills = torch.arange(num_skills, device=env.device).repeat(episodes_per_skill)
    transform = skill_transforms[0]
    transform.pin(skills)
    try:
        with torch.no_grad(), set_exploration_type(exploration), torch_threads_beside_physics(env):
            rollout = env.rollout(horizon, policy, break_when_any_done=False)
    finally:
        transform.pin(None)
    out = final_states(rollout, env_name)
    out.set("skill", skills)
    return out


def convex_hull_area(points: torch.Tensor) -> float:
    """Area of the convex hull of 2-D ``points`` [N, 2] (Andrew's monotone chain); 0 for fewer than 3 points."""
    pts = sorted(set(map(tuple, points.double().tolist())))
    if len(pts) < 3:
        return 0.0

    def cross(o, a, b):
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    def half(seq):
        chain = []
        for p in seq:
            while len(chain) >= 2 and cross(chain[-2], chain[-1], p) <= 0:
                chain.pop()
            chain.append(p)
        return chain[:-1]

    hull = half(pts) + half(reversed(pts))
    return 0.5 * abs(sum(a[0] * b[1] - b[0] * a[1] for a, b in zip(hull, hull[1:] + hull[:1])))


def skill_centroids(points: torch.Tensor, skills: torch.Tensor, num_skills: int) -> torch.Tensor:
    """Per-skill mean of ``points`` ``[N, d]`` grouped by ``skills`` ``[N]`` (long, in ``[0, num_skills)``):
    ``[num_skills, d]``, NaN for a skill without points."""
    counts = torch.bincount(skills, minlength=num_skills).unsqueeze(-1).to(points.dtype)
    return points.new_zeros(num_skills, points.shape[-1]).index_add_(0, skills, points) / counts


def _mean_pairwise_distance(points: torch.Tensor) -> float:
    if points.shape[0] < 2:
        return 0.0
    distances = torch.cdist(points.double(), points.double())
    n = points.shape[0]
    return float(distances.sum() / (n * (n - 1)))


def coverage_metrics(result: TensorDictBase, num_skills: int, discriminator: Callable | None = None,
                     eval_tasks: torch.Tensor | None = None) -> dict:
    """Scalars from :func:`evaluate_skills`' output.

    Keys: ``end_pairwise_distance`` (all rollouts), ``centroid_pairwise_distance`` (per-skill mean end points),
    ``centroid_hull_area`` (2-D) or ``centroid_std`` / ``centroid_range`` (1-D), ``within_skill_std`` (mean over
    skills of the end points' std), with a ``discriminator`` (a TensorDictModule over the observation) the
    ``final_state_accuracy`` of argmax D(z|s_T), and with ``eval_tasks`` ``[M, d]`` (the held-out tasks in the
    coverage coordinates: goals, target velocities) ``task_distance_median`` / ``task_distance_max``: over the
    tasks, the distance from each to the nearest skill centroid (how well the skills cover the evaluation tasks).
    """
    end = result.get("end_point").float()
    skills = result.get("skill")
    centroids = skill_centroids(end, skills, num_skills)
    # per skill, the norm of the end points' (population) std over the coordinates
    spread = skill_centroids((end - centroids[skills]).square(), skills, num_skills).sqrt().norm(dim=-1)
    metrics = {
        "end_pairwise_distance": _mean_pairwise_distance(end),
        "centroid_pairwise_distance": _mean_pairwise_distance(centroids),
        "within_skill_std": float(spread.mean()),
    }
    if end.shape[-1] == 2:
        metrics["centroid_hull_area"] = convex_hull_area(centroids)
    else:
        metrics["centroid_std"] = float(centroids.std(unbiased=False))
        metrics["centroid_range"] = float(centroids.max() - centroids.min())
    if discriminator is not None:
        obs = result.get("final_observation")
        with torch.no_grad():
            logits = discriminator_logits(discriminator, obs)
        metrics["final_state_accuracy"] = float((logits.argmax(-1) == skills).float().mean())
    if eval_tasks is not None:
        nearest = torch.cdist(eval_tasks.double().to(centroids.device), centroids.double()).min(-1).values
        metrics["task_distance_median"] = float(nearest.median())
        metrics["task_distance_max"] = float(nearest.max())
    return metrics


def visited_states(batch: TensorDictBase, env_name: str) -> torch.Tensor:
    """``[M, d]`` coverage coordinates (the env's ``coverage_key``: x-y positions, forward velocities) at the valid
    steps of a batch of trajectories (``("next", key)`` ``[..., H, d]``, ``"mask"`` ``[..., H]``)."""
    return batch["next", get_env_spec(env_name).coverage_key][batch["mask"]]


def _cell(env_name: str, cell_size: float | None) -> float:
    return cell_size if cell_size is not None else get_env_spec(env_name).coverage_cell


def state_coverage(batch: TensorDictBase, env_name: str, cell_size: float | None = None) -> dict[str, float]:
    """Coverage of the states visited in ``batch`` (see :func:`visited_states`).

    2-D coordinates: ``cells`` (distinct grid cells of side ``cell_size``, default the env's ``coverage_cell``),
    ``area`` (cells x cell area), ``max_distance`` from the origin. 1-D (velocities): ``velocity_range`` (max - min)
    and ``velocity_range_p5_p95``.
    """
    values = visited_states(batch, env_name)
    if values.shape[-1] == 1:
        v = values.reshape(-1)
        low, high = torch.quantile(v, torch.tensor([0.05, 0.95], device=v.device))
        return {"velocity_range": float(v.max() - v.min()), "velocity_range_p5_p95": float(high - low)}
    cell = _cell(env_name, cell_size)
    cells = torch.unique(torch.floor(values / cell).long(), dim=0).shape[0]
    return {"cells": float(cells), "area": cells * cell**2, "max_distance": float(values.norm(dim=-1).max())}


def cumulative_coverage(
    seen: torch.Tensor | None, batch: TensorDictBase, env_name: str, cell_size: float | None = None
) -> tuple[torch.Tensor, dict[str, float]]:
    """Fold ``batch`` into everything visited so far: ``seen`` is the set of visited cells ``[M, 2]`` (2-D) or the
    ``[min, max]`` velocity (1-D), ``None`` at first. Returns the new ``seen`` and ``cumulative_cells`` / ``_area``
    or ``cumulative_velocity_range``."""
    values = visited_states(batch, env_name)
    if values.shape[-1] == 1:
        v = values.reshape(-1)
        seen = torch.stack([v.min(), v.max()]) if seen is None else torch.stack(
            [torch.minimum(seen[0], v.min()), torch.maximum(seen[1], v.max())])
        return seen, {"cumulative_velocity_range": float(seen[1] - seen[0])}
    cell = _cell(env_name, cell_size)
    cells = torch.floor(values / cell).long()
    seen = torch.unique(cells if seen is None else torch.cat([seen, cells]), dim=0)
    return seen, {"cumulative_cells": float(seen.shape[0]), "cumulative_area": seen.shape[0] * cell**2}


def plot_coverage(
    points: torch.Tensor,
    path: str | os.PathLike,
    *,
    eval_tasks: torch.Tensor | None = None,
    skills: torch.Tensor | None = None,
    baseline: torch.Tensor | None = None,
    label: str = "skills",
    baseline_label: str = "random policy",
    title: str = "",
) -> str:
    """Save the coverage figure of ``points`` ``[N, d]`` (skill end points, or visited states) as a PNG at ``path``
    and return the path.

    2-D: a scatter of the points (coloured by ``skills`` ``[N]`` with per-skill centroids if given), the held-out
    ``eval_tasks`` ``[M, 2]`` as red crosses and ``baseline`` points ``[K, 2]`` in grey. 1-D (velocities):
    histograms of the points (blue), of the evaluation velocities (green) and of the baseline (grey). The tensors may
    live on any device: they are copied to the CPU for plotting.
    """
    from matplotlib import colormaps
    from matplotlib.figure import Figure

    end = points.float().cpu()
    eval_tasks, skills, baseline = (None if t is None else t.cpu() for t in (eval_tasks, skills, baseline))
    fig = Figure(figsize=(6, 5))
    ax = fig.subplots()
    if end.shape[-1] == 2:
        if baseline is not None:
            ax.scatter(baseline[:, 0], baseline[:, 1], s=6, c="0.7", label=baseline_label)
        if skills is not None:
            num_skills = int(skills.max()) + 1
            colors = colormaps["hsv"](torch.linspace(0, 1, num_skills + 1)[:-1].numpy())
            ax.scatter(end[:, 0], end[:, 1], s=8, c=colors[skills.numpy()], alpha=0.6)
            centroids = skill_centroids(end, skills, num_skills)
            ax.scatter(centroids[:, 0], centroids[:, 1], s=40, c=colors, edgecolors="k", label=f"{label} centroids")
        else:
            ax.scatter(end[:, 0], end[:, 1], s=4, c="tab:red", alpha=0.4, label=label)
        if eval_tasks is not None:
            ax.scatter(eval_tasks[:, 0], eval_tasks[:, 1], marker="x", c="r", s=50, label="eval goals")
        ax.set_xlabel("x")
        ax.set_ylabel("y")
        ax.set_aspect("equal", adjustable="datalim")
    else:
        values = {label: (end[:, 0].numpy(), "tab:blue", 0.6)}
        if eval_tasks is not None:
            values["eval goal velocities"] = (eval_tasks[:, 0].numpy(), "tab:green", 0.6)
        if baseline is not None:
            values[baseline_label] = (baseline[:, 0].float().numpy(), "0.6", 0.5)
        low = min(float(v.min()) for v, _, _ in values.values())
        high = max(float(v.max()) for v, _, _ in values.values())
        bins = torch.linspace(low, high + 1e-6, 31).numpy()
        for name, (v, color, alpha) in values.items():
            ax.hist(v, bins=bins, color=color, alpha=alpha, label=name)
        ax.set_xlabel("forward velocity")
        ax.set_ylabel("count")
    ax.legend(loc="best", fontsize=8)
    ax.set_title(title)
    return str(save_figure(fig, path))
