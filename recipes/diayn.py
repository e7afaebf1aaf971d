"""DIAYN on a reward-free env: skill-conditioned SAC + a skill discriminator (the UMRL task proposal).

    python recipes/diayn.py env.name=point_nav                       # 50 skills, docs/protocol.md defaults
    python recipes/diayn.py env.name=half_cheetah logger.backend=csv
    python recipes/diayn.py env.name=point_nav resume=true           # continue from the latest checkpoint
    python recipes/diayn.py env.name=half_cheetah seeds=[0,1,2]      # three seeds in one program

The checkout's name for ``umrl diayn`` (:mod:`umrl.cli.diayn`): the same Hydra app, overrides and config
(``umrl/configs/diayn.yaml``; ``--cfg job`` prints the resolved one).
"""
from umrl.cli import run

if __name__ == "__main__":
    run("diayn")
