"""Your own environment: gymnasium's Hopper-v5 (not one of umrl's envs) with a family of target forward speeds,
through DIAYN -> MAML on the DIAYN skills (UML-DIAYN) -> meta-test on held-out speeds, beside learning from scratch.

    python examples/own_env.py [output_dir]      # default outputs/own_env; toy budgets, a few minutes on 2 cores

Importing this file registers ``gym:Hopper-v5`` with its task family, so the command lines can use it too
(docs/own_env.md)::

    python recipes/diayn.py +profile=diayn_tiny env.module=examples/own_env.py env.name=gym:Hopper-v5
    python recipes/maml.py +profile=maml_tiny proposal=diayn env.module=examples/own_env.py env.name=gym:Hopper-v5
"""
import sys

import torch

import umrl.trainers
from umrl.envs import TaskFamily, register_env
from umrl.envs.gym_cmp import gym_env_spec
from umrl.metatest import AdaptationConfig, CellSpec, curves_from_rows, read_rows, run_cell
from umrl.process import torch_threads

METHODS = ("uml_diayn", "scratch")


def speed_reward(next_td, action: torch.Tensor, task: torch.Tensor) -> torch.Tensor:
    """``1 - |v_x - v| - 0.001 ||a||^2`` ``[B, 1]``: run at the task's speed ``v`` (``task`` ``[B, 1]``); the 1 per
    step is Hopper's healthy reward, so that falling over (which ends the episode) never pays."""
    return 1.0 - (next_td["x_velocity"] - task).abs() - 1e-3 * action.pow(2).sum(-1, keepdim=True)


HOPPER = register_env(gym_env_spec(
    "Hopper-v5",
    TaskFamily("hopper", task_dim=1, low=0.0, high=1.5, reward_fn=speed_reward),  # target speeds U[0, 1.5]
    physics={"x_velocity": "x_velocity", "x_position": "x_position"},  # gymnasium's info names
    coverage_reduction="mean",  # a skill's coverage: its mean forward speed
), overwrite=True)  # importing this file twice (an example, then env.module) registers the same record


def own_env(out="outputs/own_env", *, diayn=(), maml=(), steps=3, num_tasks=5, trajectories=5, horizon=50) -> dict:
    """Mean meta-test return of UML-DIAYN and of scratch on ``num_tasks`` held-out speeds after k = 0..steps
    updates of ``trajectories`` trajectories of ``horizon`` steps per task, ``{method: [return at k]}``; MAML
    meta-trains on trajectories of that length; ``diayn``/``maml``: extra overrides of the tiny profiles."""
    env = [f"env.name={HOPPER.name}"]
    with torch_threads(1):  # opt-in, restored on exit: the configs' num_threads, as the command lines apply it
        umrl.trainers.train("diayn", ["+profile=diayn_tiny", *env, f"output_dir={out}/diayn", "progress=false",
                                      *diayn])
        run = umrl.trainers.train("maml", ["+profile=maml_tiny", *env, f"env.horizon={horizon}", "proposal=diayn",
                                           f"trajectories_per_task={trajectories}", f"diayn_checkpoint={out}/diayn",
                                           f"output_dir={out}/maml", "progress=false", *maml])
        protocol = AdaptationConfig(num_steps=steps, num_trajectories=trajectories, horizon=horizon)
        cells = [CellSpec(method=method, env=HOPPER.name, seed=0, checkpoint=checkpoint, num_tasks=num_tasks,
                          protocol=protocol, output=f"{out}/meta_test_{method}.csv")
                 for method, checkpoint in zip(METHODS, (run["checkpoint"], None))]
        curves = curves_from_rows(read_rows([run_cell(cell) for cell in cells]))[HOPPER.name]
    return {method: curves[method].mean.tolist() for method in METHODS}


if __name__ == "__main__":
    returns = own_env(*sys.argv[1:2])
    speeds = ", ".join(f"{v:.2f}" for v in HOPPER.eval_tasks()[:5, 0].tolist())
    print(f"Hopper-v5, mean return on 5 held-out target speeds ({speeds}) after k policy-gradient steps")
    print("(toy budgets: the pipeline, not a result)")
    for k, (uml, scratch) in enumerate(zip(returns["uml_diayn"], returns["scratch"])):
        print(f"  k = {k}: UML-DIAYN {uml:7.1f}   scratch {scratch:7.1f}")
