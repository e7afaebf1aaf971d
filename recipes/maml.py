"""MAML meta-training on proposed tasks: UML-DIAYN, UML-random, or the oracle task family.

    python recipes/maml.py proposal=oracle                                   # hand-designed goals (upper bound)
    python recipes/maml.py proposal=diayn diayn_checkpoint=outputs/diayn/point_nav/seed0
    python recipes/maml.py proposal=random resume=true                       # continue from the latest checkpoint

The checkout's name for ``umrl maml`` (:mod:`umrl.cli.maml`): the same Hydra app, overrides and config
(``umrl/configs/maml.yaml``; ``--cfg job`` prints the resolved one).
"""
from umrl.cli import run

if __name__ == "__main__":
    run("maml")
