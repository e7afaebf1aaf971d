"""The benchmark suite's command line: does unsupervised meta-learning make RL faster here?

    python benchmarks/suite.py profile=tiny                      # every method at toy budgets (~140 CPU-seconds)
    python benchmarks/suite.py profile=quick                     # point_nav, reduced budgets, minutes on 2 cores
    python benchmarks/suite.py profile=reference envs=[point_nav]  # the reference code's settings
    python benchmarks/suite.py profile=quick launcher.ray_address=auto   # jobs as Ray tasks on a cluster
    python benchmarks/suite.py profile=quick device=auto         # pre-training and meta-test on a GPU if there is one

The checkout's name for ``umrl suite`` (:mod:`umrl.cli.suite`, over :func:`umrl.suite.run_suite`): the same Hydra
app, overrides and config (``umrl/suite/config/``: ``suite.yaml`` and the ``profile/`` presets).
"""
from umrl.cli import run

if __name__ == "__main__":
    run("suite")
