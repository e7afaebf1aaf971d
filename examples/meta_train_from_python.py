"""Meta-train a policy with UML-random and meta-test it on held-out tasks, from Python only (no recipes, no Hydra app).

    python examples/meta_train_from_python.py                 # tiny sizes: about a minute on 2 CPU cores
    python examples/meta_train_from_python.py --output outputs/example --iterations 20

Each block below is one notebook cell. The sizes are tiny so it runs in a test; the defaults of every setting are in
``umrl/configs/maml.yaml`` and ``umrl.metatest.AdaptationConfig`` (docs/protocol.md says where each comes from).
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import torch

from umrl.envs import get_env_spec
from umrl.metatest import AdaptationConfig, load_initialisation, meta_test
from umrl.process import tune_process
from umrl.trainers import MAMLTrainer, compose


def meta_train(output_dir: Path, *, iterations: int) -> Path:
    """UML-random on point_nav: MAML on the tasks a frozen random discriminator proposes; returns the run dir."""
    cfg = compose("maml", [
        "proposal=random", "env.name=point_nav", "env.horizon=20", "num_skills=4", "meta_batch_size=4",
        "trajectories_per_task=4", "policy.hidden=[32,32]", f"iterations={iterations}", "checkpoint.every=1",
        "logger.backend=none", "progress=false", f"output_dir={output_dir}",
    ])
    trainer = MAMLTrainer(cfg)
    try:
        first = trainer.step()  # one meta-iteration by hand: its metrics come back as a dict
        trainer.save()  # steps by hand are checkpointed by hand (train() does it every checkpoint.every)
        print(f"iteration 1: return pre {first['train/return_pre']:.2f} -> post {first['train/return_post']:.2f}")
        result = trainer.train()  # the rest of the budget, checkpointed
        print(f"iteration {result['iteration']}: checkpoint {result['checkpoint']}")
    finally:
        trainer.close()
    return output_dir


def evaluate(run_dir: Path, *, num_tasks: int, num_steps: int) -> torch.Tensor:
    """Adapt the meta-trained initialisation on held-out point_nav goals; returns the mean return per step."""
    init = load_initialisation("uml_random", "point_nav", run_dir, seed=0)
    tasks = get_env_spec("point_nav").eval_tasks()[:num_tasks]
    config = AdaptationConfig(num_steps=num_steps, num_trajectories=4, horizon=20)
    returns, _ = meta_test(init, "point_nav", tasks, lr=init.lr, seed=0, config=config, skill_trajectories=1)
    return returns.mean(-1)  # [K + 1]: mean over tasks at every adaptation step


def main(argv: list[str] | None = None) -> torch.Tensor:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--output", type=Path, default=None, help="run directory (default: a temporary one)")
    parser.add_argument("--iterations", type=int, default=2)
    parser.add_argument("--tasks", type=int, default=3)
    parser.add_argument("--steps", type=int, default=2, help="meta-test adaptation steps K")
    args = parser.parse_args(argv)
    tune_process(num_threads=1)  # this script owns its process: umrl's process-wide tuning is opt-in
    with tempfile.TemporaryDirectory() as scratch:
        run_dir = meta_train(args.output or Path(scratch) / "maml", iterations=args.iterations)
        curve = evaluate(run_dir, num_tasks=args.tasks, num_steps=args.steps)
    print("meta-test mean return per adaptation step:", [round(v, 2) for v in curve.tolist()])
    return curve


if __name__ == "__main__":
    main()
