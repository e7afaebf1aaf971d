"""umrl: unsupervised meta-reinforcement learning on TorchRL.

Subpackages, lowest layer first (each imports only from the ones before it): :mod:`umrl.envs` (environments and
their registry, task families), :mod:`umrl.transforms`, :mod:`umrl.modules`, :mod:`umrl.objectives` and
:mod:`umrl.optim`, :mod:`umrl.rollout`, :mod:`umrl.checkpoints`, :mod:`umrl.metatest` and :mod:`umrl.configs`,
:mod:`umrl.trainers` (training as library objects), :mod:`umrl.suite` (the benchmark suite), :mod:`umrl.cli` (the
``umrl`` command line; ``recipes/*.py`` and ``benchmarks/suite.py`` are its checkout names).

Importing umrl changes nothing process-wide; the process tuning umrl's command lines apply is opt-in
(:mod:`umrl.process`).
"""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("umrl")
except PackageNotFoundError:  # a source tree used without being installed
    __version__ = "0+unknown"
