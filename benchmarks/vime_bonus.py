"""Time VIME's information-gain bonus for a batch of transitions against the time of collecting that batch.

    python benchmarks/vime_bonus.py                       # point_nav, 40 x 100 = 4000 transitions, 5 repeats
    python benchmarks/vime_bonus.py --env half_cheetah --repeats 3

Both are measured in the same process, interleaved (collect, then score that batch), and reported as medians: the
collection is :func:`umrl.rollout.collect` with the 2x300 Gaussian policy, the bonus is
:class:`umrl.transforms.vime_bonus.VIMEBonus` on the whole ``[N, H]`` batch (one ``vmap(grad)`` over transitions,
10 weight samples, a 32-unit Bayesian dynamics net). On a shared CPU the absolute numbers are noisy; the ratio
measured in one run is the figure to quote.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from umrl.envs import ENV_NAMES, make_env
from umrl.modules.bnn import BayesianDynamics
from umrl.modules.policy import make_gaussian_policy
from umrl.process import tune_process
from umrl.rollout import collect
from umrl.transforms.vime_bonus import VIMEBonus


def run(env_name: str, num_envs: int, horizon: int, repeats: int, num_samples: int) -> dict[str, float]:
    torch.manual_seed(0)
    env = make_env(env_name, num_envs, seed=0, horizon=horizon)
    obs_dim, act_dim = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    policy = make_gaussian_policy(obs_dim, act_dim)
    bonus = VIMEBonus(BayesianDynamics(obs_dim, act_dim), num_samples=num_samples)
    collect_s, bonus_s = [], []
    for i in range(repeats + 1):  # the first round warms up both paths and is discarded
        tic = time.perf_counter()
        batch = collect(env, policy, num_tasks=1, horizon=horizon)[0]
        t_collect = time.perf_counter() - tic
        if i == 0:
            bonus.dynamics.update_normalizer(batch["observation"], batch["action"], batch["next", "observation"])
        tic = time.perf_counter()
        bonus(batch)
        t_bonus = time.perf_counter() - tic
        if i > 0:
            collect_s.append(t_collect)
            bonus_s.append(t_bonus)
    env.close()
    collect_med, bonus_med = statistics.median(collect_s), statistics.median(bonus_s)
    return {"transitions": num_envs * horizon, "collect_s": collect_med, "bonus_s": bonus_med,
            "bonus_over_collect": bonus_med / collect_med}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--env", default="point_nav", choices=ENV_NAMES)
    parser.add_argument("--num-envs", type=int, default=40)
    parser.add_argument("--horizon", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--num-samples", type=int, default=10, help="weight samples for the information gain")
    parser.add_argument("--threads", type=int, default=None, help="torch.set_num_threads (default: torch's)")
    args = parser.parse_args()
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    tune_process()  # as the recipes run
    result = run(args.env, args.num_envs, args.horizon, args.repeats, args.num_samples)
    print(f"{args.env}: {result['transitions']} transitions, threads={torch.get_num_threads()}, "
          f"median of {args.repeats}: collect {result['collect_s']:.3f} s, bonus {result['bonus_s']:.3f} s, "
          f"bonus/collect = {result['bonus_over_collect']:.2f}")


if __name__ == "__main__":
    main()
