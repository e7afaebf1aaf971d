"""Where an initialisation's k = 0 policy goes on an env's evaluation tasks, against scratch's.

    python recipes/vime.py output_dir=outputs/vime/point_nav/seed0 logger.backend=csv progress=false
    python scripts/diagnostics/initial_policy.py --method vime_init --checkpoint outputs/vime/point_nav/seed0

A diagnostic, not a method: the initialisation is loaded as the suite's meta-test loads it
(:func:`umrl.metatest.methods.load_initialisation`, meta-test seed ``--seed``) and rolled out once, unadapted, on the
env's evaluation tasks (``--trajectories`` per task, the env's horizon); scratch's fresh init beside it. Printed per
policy: its action log-std (mean over dimensions), the mean |loc| of its Gaussian and the share of sampled action
entries outside the env's [-1, 1] bounds (which the env clips, so a score-function step moves them without moving
the executed action), the mean distance of the final position from the start (``--position-key``), and the mean
return at k = 0.
"""
from __future__ import annotations

import argparse

import torch

from umrl.envs import get_env_spec
from umrl.metatest import make_eval_env
from umrl.metatest.methods import METHODS, load_initialisation
from umrl.modules.policy import policy_log_std
from umrl.objectives.policy_gradient import episode_mean, episode_returns
from umrl.rollout import collect


def describe(method: str, checkpoint: str | None, env_name: str, *, seed: int, trajectories: int,
             position_key: str) -> str:
    """One line: log-std, mean |loc|, clipped share, end distance from the start and the k = 0 return."""
    spec = get_env_spec(env_name)
    tasks = spec.eval_tasks()
    init = load_initialisation(method, env_name, checkpoint, seed=seed)
    torch.manual_seed(seed)
    env = make_eval_env(env_name, tasks, trajectories, seed=seed, horizon=spec.horizon)
    batch = collect(env, init.policy, num_tasks=tasks.shape[0], horizon=spec.horizon)
    env.close()
    mask = batch["mask"].unsqueeze(-1)
    positions = batch["next", position_key]
    last = positions.gather(-2, (batch["mask"].sum(-1, keepdim=True) - 1).clamp_min(0).unsqueeze(-1).expand(
        *positions.shape[:-2], 1, positions.shape[-1])).squeeze(-2)
    start = batch[position_key][..., 0, :]
    clipped = ((batch["action"].abs() > 1) & mask).sum() / (mask.sum() * batch["action"].shape[-1])
    returns = episode_mean(episode_returns(batch), batch).mean()
    return (f"{method}: log-std {policy_log_std(init.policy).mean().item():.3f}, mean |loc| "
            f"{(batch['loc'].abs() * mask).sum().item() / (mask.sum().item() * batch['loc'].shape[-1]):.2f}, "
            f"actions outside the bounds {clipped.item():.2f}, end distance from the start "
            f"{(last - start).norm(dim=-1).mean().item():.2f}, return k=0 {returns.item():.1f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--method", required=True, choices=sorted(METHODS))
    parser.add_argument("--checkpoint", default=None, help="its pre-training run dir or step_*.safetensors (not for scratch)")
    parser.add_argument("--env", default="point_nav")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--trajectories", type=int, default=40)
    parser.add_argument("--position-key", default="position", help="the env's position physics key")
    args = parser.parse_args()
    for method, checkpoint in ((args.method, args.checkpoint), ("scratch", None)):
        print(describe(method, checkpoint, args.env, seed=args.seed, trajectories=args.trajectories,
                       position_key=args.position_key))


if __name__ == "__main__":
    main()
