"""VIME pre-training: TRPO on the information-gain bonus alone (the VIME-init baseline's policy).

    python recipes/vime.py env.name=point_nav                     # 30 iterations of 40 x 100 steps
    python recipes/vime.py env.name=half_cheetah logger.backend=csv
    python recipes/vime.py env.name=point_nav resume=true         # continue from the latest checkpoint

The checkout's name for ``umrl vime`` (:mod:`umrl.cli.vime`): the same Hydra app, overrides and config
(``umrl/configs/vime.yaml``; ``--cfg job`` prints the resolved one).
"""
from umrl.cli import run

if __name__ == "__main__":
    run("vime")
