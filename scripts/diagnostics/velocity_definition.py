"""half_cheetah's forward velocity two ways: umrl's (gymnasium's) against the MAML reference code's.

    python scripts/diagnostics/velocity_definition.py --episodes 20 --steps 100 --seed 0

A diagnostic, not a method. umrl's target-velocity reward reads ``x_velocity``: the root's x displacement over the
0.05 s control step (``HalfCheetah-v5``'s definition). cbfinn/maml_rl's ``half_cheetah_env_rand.py`` reads
``get_body_comvel("torso")[0]`` after the step: rllab's mass-weighted mean of every body's linear velocity
(``mj_objectVelocity``) over the torso's subtree, the whole cheetah. Both are computed here on the same
``HalfCheetah-v5`` trajectories (uniform random actions, the env's own reset noise), the reference's on a copy of
the post-step state (rllab calls ``model.forward()`` after stepping). For targets drawn from the task family
U[0, 2], it prints the two velocities' means and spread, their mean absolute difference and correlation, and the
mean absolute difference of the reward term −|v_x − v| per step and of its sum over an episode.
"""
from __future__ import annotations

import argparse

import gymnasium
import mujoco
import numpy as np


def reference_comvel(model: mujoco.MjModel, data: mujoco.MjData, body: int) -> float:
    """rllab's ``body_comvels[body][0]`` (``rllab/mujoco_py/mjcore.py``): subtree-mass-weighted body velocities."""
    velocity = np.zeros(6)
    momentum = np.zeros((model.nbody, 3))
    for i in range(model.nbody):
        mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, i, velocity, 0)
        momentum[i] = velocity[3:] * model.body_mass[i]
    mass = model.body_mass.copy()
    for i in range(model.nbody - 1, 0, -1):
        parent = model.body_parentid[i]
        momentum[parent] += momentum[i]
        mass[parent] += mass[i]
    return float(momentum[body, 0] / mass[body])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    env = gymnasium.make("HalfCheetah-v5")
    model = env.unwrapped.model
    torso = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, "torso")
    after = mujoco.MjData(model)
    rng = np.random.default_rng(args.seed)
    umrl_v, reference_v, targets = [], [], []
    for episode in range(args.episodes):
        env.reset(seed=args.seed * 100_000 + episode)
        targets.append(rng.uniform(0.0, 2.0))
        for _ in range(args.steps):
            _, _, _, _, info = env.step(rng.uniform(-1.0, 1.0, size=model.nu))
            data = env.unwrapped.data
            after.qpos[:], after.qvel[:], after.time = data.qpos, data.qvel, data.time
            mujoco.mj_forward(model, after)
            umrl_v.append(info["x_velocity"])
            reference_v.append(reference_comvel(model, after, torso))
    umrl_v = np.asarray(umrl_v).reshape(args.episodes, args.steps)
    reference_v = np.asarray(reference_v).reshape(args.episodes, args.steps)
    goal = np.asarray(targets)[:, None]
    reward_gap = np.abs(np.abs(umrl_v - goal) - np.abs(reference_v - goal))
    return_gap = np.abs((np.abs(umrl_v - goal) - np.abs(reference_v - goal)).sum(1))
    print(f"HalfCheetah-v5, {args.episodes} episodes x {args.steps} steps of uniform random actions, seed {args.seed}")
    print(f"umrl x_velocity:       mean {umrl_v.mean():+.3f}, std {umrl_v.std():.3f}")
    print(f"reference comvel:      mean {reference_v.mean():+.3f}, std {reference_v.std():.3f}")
    print(f"mean |difference|:     {np.abs(umrl_v - reference_v).mean():.3f}; "
          f"correlation {np.corrcoef(umrl_v.ravel(), reference_v.ravel())[0, 1]:.3f}")
    print(f"reward term -|v_x - v|, v ~ U[0, 2]: mean |difference| per step {reward_gap.mean():.3f}, "
          f"per {args.steps}-step episode {return_gap.mean():.2f} (median {np.median(return_gap):.2f})")
    env.close()


if __name__ == "__main__":
    main()
