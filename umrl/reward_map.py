"""Where a skill discriminator's tasks point: territories and rewards r_z(s) = log D(z|s) - log p(z) over 2-D states.

For a discriminator on point_nav's 2-D observation (a frozen random one for UML-random, or a trained DIAYN one), this
module evaluates every skill's pseudo-reward over

- a square grid ``[-R, R]²`` covering the region a policy can reach in one episode (R = horizon x 0.1 on point_nav),
  whose argmax over skills is each skill's *territory*;
- polar samples of the disc of radius R (rings x angles), so "the best point within radius R is on the edge" is exact;
- grids of the evaluation goal square and of ``[-1, 1]²``, and the held-out evaluation goals.

:func:`reward_map_stats` turns these into the numbers that explain UML-random's tasks: how much each
skill's reward varies inside the goal square against the whole reachable disc, the fraction of skills whose best
reachable point is on the disc's edge ("run as far as possible in one direction"), and how many skills win somewhere
near the origin. :func:`plot_territories` and :func:`plot_rays` draw the figures.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import torch
from tensordict.nn import TensorDictModuleBase

from umrl.figures import save_figure
from umrl.modules.discriminator import discriminator_logits
from umrl.transforms.discriminator_reward import skill_rewards

__all__ = ["RewardMap", "plot_rays", "plot_territories", "pseudo_rewards", "reward_map", "reward_map_stats"]


@torch.no_grad()
def pseudo_rewards(discriminator: TensorDictModuleBase, points: torch.Tensor) -> torch.Tensor:
    """r_z(s) = log_softmax(D(s))[z] + log K for every skill: points ``[*B, 2]`` -> rewards ``[*B, K]`` (on CPU).

    The discriminator reads one key (observation ``[*B, obs_dim]``) and writes one (logits ``[*B, K]``); points are
    moved to its parameters' device.
    """
    param = next(discriminator.parameters(), None)
    device = points.device if param is None else param.device
    return skill_rewards(discriminator_logits(discriminator, points.to(device))).cpu()


def square_grid(half_width: float, resolution: int) -> torch.Tensor:
    """``[resolution, resolution, 2]`` points covering ``[-half_width, half_width]²``; ``[i, j] = (x_j, y_i)``."""
    axis = torch.linspace(-half_width, half_width, resolution)
    y, x = torch.meshgrid(axis, axis, indexing="ij")
    return torch.stack([x, y], -1)


def ray_points(radius: float, num_angles: int, num_radii: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(points [A, M, 2], angles [A], radii [M])``: M distances in ``[0, radius]`` along A rays from the origin."""
    angles = torch.arange(num_angles) * (2 * math.pi / num_angles)
    radii = torch.linspace(0.0, radius, num_radii)
    points = radii[None, :, None] * torch.stack([angles.cos(), angles.sin()], -1)[:, None, :]
    return points, angles, radii


@dataclass
class RewardMap:
    """A discriminator's pseudo-rewards on point_nav's reachable region (all tensors on CPU; K skills).

    Attributes:
        radius: R, the reach of one episode.
        grid: ``[G, G, 2]`` points of ``[-R, R]²``; ``grid_rewards`` ``[G, G, K]``; ``territory`` ``[G, G]`` (argmax
            over skills).
        angles ``[A]``, radii ``[M]``: the polar samples of the disc of radius R; ``ray_rewards`` ``[A, M, K]``.
        goal_half_width: half side of the evaluation goal square; ``goal_rewards`` ``[Gg, Gg, K]`` on its grid.
        inner_half_width: half side of the near-origin square; ``inner_territory`` ``[Gi, Gi]`` on its grid.
        eval_goals ``[N, 2]``; ``eval_goal_rewards`` ``[N, K]``.
    """

    radius: float
    grid: torch.Tensor
    grid_rewards: torch.Tensor
    territory: torch.Tensor
    angles: torch.Tensor
    radii: torch.Tensor
    ray_rewards: torch.Tensor
    goal_half_width: float
    goal_rewards: torch.Tensor
    inner_half_width: float
    inner_territory: torch.Tensor
    eval_goals: torch.Tensor
    eval_goal_rewards: torch.Tensor

    @property
    def num_skills(self) -> int:
        return self.grid_rewards.shape[-1]


def reward_map(
    discriminator: TensorDictModuleBase,
    eval_goals: torch.Tensor,
    *,
    radius: float,
    goal_half_width: float = 0.5,
    inner_half_width: float = 1.0,
    resolution: int = 201,
    num_angles: int = 72,
    num_radii: int = 101,
) -> RewardMap:
    """Evaluates ``discriminator`` (2-D observation -> K logits) on the grids and rays described in the module doc.

    Args:
        discriminator: D(z|s) reading a 2-D observation.
        eval_goals: ``[N, 2]`` held-out goals (``get_task_family("point_nav").eval_tasks()``).

    Keyword Args:
        radius: R > 0, the reachable region (grid ``[-R, R]²``, disc of radius R).
        goal_half_width / inner_half_width: the evaluation goal square ``[-0.5, 0.5]²`` and the near-origin square
            ``[-1, 1]²`` by default.
        resolution: grid points per axis (each grid); num_angles / num_radii: the polar samples.
    """
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius}.")
    if eval_goals.ndim != 2 or eval_goals.shape[-1] != 2:
        raise ValueError(f"eval_goals must have shape [N, 2], got {tuple(eval_goals.shape)}.")
    small = {"resolution": resolution, "num_angles": num_angles, "num_radii": num_radii}
    if any(v < 2 for v in small.values()):
        raise ValueError(f"resolution, num_angles and num_radii must be >= 2, got {small}.")
    grid = square_grid(radius, resolution)
    grid_rewards = pseudo_rewards(discriminator, grid)
    points, angles, radii = ray_points(radius, num_angles, num_radii)
    return RewardMap(
        radius=radius, grid=grid, grid_rewards=grid_rewards, territory=grid_rewards.argmax(-1),
        angles=angles, radii=radii, ray_rewards=pseudo_rewards(discriminator, points),
        goal_half_width=goal_half_width, goal_rewards=pseudo_rewards(discriminator,
                                                                     square_grid(goal_half_width, resolution)),
        inner_half_width=inner_half_width,
        inner_territory=pseudo_rewards(discriminator, square_grid(inner_half_width, resolution)).argmax(-1),
        eval_goals=eval_goals.float().cpu(), eval_goal_rewards=pseudo_rewards(discriminator, eval_goals.float()),
    )


def reward_map_stats(rmap: RewardMap) -> dict[str, float]:
    """The numbers that say what a discriminator's tasks ask for (medians are over the K skills):

    - ``goal_square_range``: median over skills of max - min of r_z inside the goal square (nats);
    - ``disc_range``, ``disc_min``, ``disc_max``: median of max - min, min and max of r_z within radius R;
    - ``edge_fraction``: fraction of skills whose best point within radius R is on the edge (radius R);
    - ``skills_near_origin``: skills that are the most likely somewhere in the inner square (``[-1, 1]²``);
    - ``skills_at_eval_goals``: distinct skills that are the most likely at the N evaluation goals;
    - ``num_skills``: K.
    """
    disc = rmap.ray_rewards.flatten(0, 1)  # [A * M, K]
    goal = rmap.goal_rewards.flatten(0, 1)
    best_radius = rmap.ray_rewards.amax(0).argmax(0)  # [K]: the ring of each skill's best point
    return {
        "num_skills": rmap.num_skills,
        "goal_square_range": (goal.amax(0) - goal.amin(0)).median().item(),
        "disc_range": (disc.amax(0) - disc.amin(0)).median().item(),
        "disc_min": disc.amin(0).median().item(),
        "disc_max": disc.amax(0).median().item(),
        "edge_fraction": (best_radius == len(rmap.radii) - 1).float().mean().item(),
        "skills_near_origin": rmap.inner_territory.unique().numel(),
        "skills_at_eval_goals": rmap.eval_goal_rewards.argmax(-1).unique().numel(),
    }


def _square(ax, half_width: float, **kwargs) -> None:
    from matplotlib.patches import Rectangle

    ax.add_patch(Rectangle((-half_width, -half_width), 2 * half_width, 2 * half_width, fill=False, **kwargs))


def plot_territories(rmap: RewardMap, path: str | Path, *, title: str = "") -> Path:
    """Each skill's territory (argmax_z D(z|s)) on ``[-R, R]²`` and, zoomed, on the near-origin square, with the
    goal square and the evaluation goals; written to ``path`` (PNG)."""
    from matplotlib import colormaps
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle

    cmap = colormaps["tab20"].resampled(20)
    fig = Figure(figsize=(12, 5.5))
    axes = fig.subplots(1, 2)
    for ax, territory, half in ((axes[0], rmap.territory, rmap.radius),
                                (axes[1], rmap.inner_territory, rmap.inner_half_width)):
        ax.imshow(territory % 20, origin="lower", extent=(-half, half, -half, half), cmap=cmap, vmin=0, vmax=19,
                  interpolation="nearest")
        ax.contour(torch.linspace(-half, half, territory.shape[1]), torch.linspace(-half, half, territory.shape[0]),
                   territory, levels=torch.arange(rmap.num_skills + 1).float() - 0.5, colors="k", linewidths=0.3)
        _square(ax, rmap.goal_half_width, edgecolor="red", linewidth=1.5)
        ax.scatter(rmap.eval_goals[:, 0], rmap.eval_goals[:, 1], marker="x", c="red", s=25, label="eval goals")
        ax.set_aspect("equal")
    _square(axes[0], rmap.inner_half_width, edgecolor="k", linestyle="--")
    axes[0].add_patch(Circle((0, 0), rmap.radius, fill=False, edgecolor="k", linestyle=":"))
    axes[0].set_title(f"territories on [-{rmap.radius:g}, {rmap.radius:g}]² (colour = skill mod 20)")
    axes[1].set_title(f"[-{rmap.inner_half_width:g}, {rmap.inner_half_width:g}]²: "
                      f"{rmap.inner_territory.unique().numel()} of {rmap.num_skills} skills win here")
    axes[1].legend(loc="upper right")
    fig.suptitle(title)
    return save_figure(fig, path, dpi=110)


def plot_rays(rmap: RewardMap, path: str | Path, *, skills: int = 4, rays: int = 8, title: str = "") -> Path:
    """r_z along ``rays`` evenly spaced rays from the origin (x: distance) for ``skills`` skills (one panel each),
    with the goal square's half width marked; written to ``path`` (PNG)."""
    from matplotlib.figure import Figure

    chosen = torch.linspace(0, rmap.num_skills - 1, min(skills, rmap.num_skills)).round().long().unique()
    step = max(1, len(rmap.angles) // rays)
    fig = Figure(figsize=(4 * len(chosen), 3.6))
    axes = fig.subplots(1, len(chosen), sharey=True, squeeze=False)
    for ax, z in zip(axes[0], chosen.tolist()):
        for a in range(0, len(rmap.angles), step):
            ax.plot(rmap.radii, rmap.ray_rewards[a, :, z], lw=1,
                    label=f"{math.degrees(rmap.angles[a].item()):.0f}°")
        ax.axvline(rmap.goal_half_width, color="red", lw=0.8, ls="--")
        ax.set_title(f"skill {z}")
        ax.set_xlabel("distance from the origin")
    axes[0][0].set_ylabel("log D(z|s) - log p(z)")
    axes[0][-1].legend(fontsize=7, title="ray angle")
    fig.suptitle(title)
    return save_figure(fig, path, dpi=110)
