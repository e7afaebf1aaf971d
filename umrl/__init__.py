"""umrl: unsupervised meta-reinforcement learning on TorchRL.

Subpackages, lowest layer first (each imports only from the ones before it): :mod:`umrl.envs` (environments and
their registry, task families), :mod:`umrl.transforms`, :mod:`umrl.modules`, :mod:`umrl.objectives` and
:mod:`umrl.optim`, :mod:`umrl.rollout`, :mod:`umrl.checkpoints`, :mod:`umrl.metatest`; the training recipes are the
``recipes`` package.

Importing umrl records absent optional packages that a dependency looks up on every module call
(:mod:`umrl.absent_modules`).
"""
from importlib.metadata import PackageNotFoundError, version

from umrl.absent_modules import mark_absent_modules

try:
    __version__ = version("umrl")
except PackageNotFoundError:  # a source tree used without being installed
    __version__ = "0+unknown"

mark_absent_modules()
