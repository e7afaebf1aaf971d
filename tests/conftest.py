"""Shared test settings: CPU, no network, deterministic threads."""
import os
import warnings

os.environ.setdefault("WANDB_MODE", "disabled")
os.environ.setdefault("HYDRA_FULL_ERROR", "1")
warnings.filterwarnings("ignore", message=".*settotalmass.*")

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture
def tiny_diayn_checkpoint(tmp_path):
    """A minimal point_nav DIAYN checkpoint (4 skills, one 16-unit discriminator layer) in ``tmp_path / "diayn"``;
    returns ``(directory, discriminator)``."""
    from umrl.checkpoints import DIAYN_FORMAT
    from umrl.modules.discriminator import make_discriminator
    from umrl.runtime import Checkpointer

    directory = tmp_path / "diayn"
    discriminator = make_discriminator(2, 4, hidden=(16,), seed=0)
    meta = {"env": "point_nav", "obs_dim": 2, "act_dim": 2, "num_skills": 4, "hidden": [16],
            "discriminator_hidden": [16], "discriminator_observation_key": ["next", "observation"]}
    DIAYN_FORMAT.save(Checkpointer(directory / "checkpoints"), 1, meta, discriminator=discriminator.state_dict())
    return directory, discriminator
