"""Checkpoint formats: each recipe's ``save_*`` beside its ``load_*``, one format/version check for all.

======  ==================  ==========================================================================
format  written by          read with
======  ==================  ==========================================================================
DIAYN   recipes/diayn.py    :func:`load_diayn_checkpoint`, :func:`load_discriminator`, :func:`load_skill_policy`
MAML    recipes/maml.py     :func:`load_maml_checkpoint`, :func:`load_maml_policy`
VIME    recipes/vime.py     :func:`load_vime_checkpoint`, :func:`load_vime_policy`, :func:`load_vime_dynamics`
======  ==================  ==========================================================================

Every loader accepts a ``step_*.safetensors`` file (or a ``step_*.pt`` one, as umrl named them before), a
``checkpoints/`` folder or a run's output_dir (the latest checkpoint), and raises ``ValueError`` for a file of another format (:class:`~umrl.checkpoints.format.CheckpointFormat`, whose
``check_run`` also refuses a run of another env or proposal than a caller expects) and its subclass
:class:`~umrl.checkpoints.file.CheckpointError`, naming the file, for one umrl cannot have written (non-finite weights
or settings, layer sizes its tensors do not have: checked before any network is built); :func:`maml_policy`,
:func:`skill_policy` and :func:`vime_policy` build the policies from a checkpoint already loaded. Files are
:mod:`umrl.checkpoints.file`'s: tensors as data, a JSON tree and a content hash, so loading one runs no code and a
changed byte is an error naming the file; the torch.save pickles of older umrl versions are refused and convert with
``python -m umrl.checkpoints.convert OLD NEW`` (:mod:`umrl.checkpoints.convert`; trusted files only: it unpickles).
:func:`export_diayn_skills` (``python -m umrl.checkpoints.export_skills SOURCE DESTINATION``) keeps a finished DIAYN
run's skills without its replay buffer; the same loaders read the copy.
"""
from umrl.checkpoints.diayn import (
    DIAYN_FORMAT,
    export_diayn_skills,
    load_diayn_checkpoint,
    load_discriminator,
    load_skill_policy,
    save_diayn_checkpoint,
    skill_policy,
)
from umrl.checkpoints.format import CheckpointFormat
from umrl.checkpoints.maml import (
    MAML_FORMAT,
    load_maml_checkpoint,
    load_maml_policy,
    maml_policy,
    save_maml_checkpoint,
)
from umrl.checkpoints.vime import (
    VIME_FORMAT,
    load_vime_checkpoint,
    load_vime_dynamics,
    load_vime_policy,
    save_vime_checkpoint,
    vime_policy,
)

__all__ = [
    "DIAYN_FORMAT",
    "MAML_FORMAT",
    "VIME_FORMAT",
    "CheckpointFormat",
    "export_diayn_skills",
    "load_diayn_checkpoint",
    "load_discriminator",
    "load_maml_checkpoint",
    "load_maml_policy",
    "load_skill_policy",
    "load_vime_checkpoint",
    "load_vime_dynamics",
    "load_vime_policy",
    "maml_policy",
    "save_diayn_checkpoint",
    "save_maml_checkpoint",
    "save_vime_checkpoint",
    "skill_policy",
    "vime_policy",
]
