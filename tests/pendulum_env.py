"""A user's env module for the tests (``env_module=tests/pendulum_env.py``): importing it registers gymnasium's
``InvertedPendulum-v5`` (4 observations, 1 action: cheap to step) with a family of target cart positions."""
from umrl.envs import TaskFamily, register_env
from umrl.envs.gym_cmp import gym_env_spec


def cart_reward(next_td, action, task):
    """Keep the cart at position ``task`` ``[B, 1]``: ``-|x - task|`` ``[B, 1]``."""
    return -(next_td["cart"] - task).abs()


PENDULUM = register_env(gym_env_spec(
    "InvertedPendulum-v5",
    TaskFamily("cart", task_dim=1, low=-0.5, high=0.5, reward_fn=cart_reward),
    physics={"cart": lambda env: env.data.qpos[:1].copy()},  # its info is empty: read from the unwrapped env
    coverage_reduction="mean",
), overwrite=True)
