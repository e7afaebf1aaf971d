"""Shared test settings: CPU, no network, deterministic threads."""
import os
import warnings

os.environ.setdefault("WANDB_MODE", "disabled")
os.environ.setdefault("HYDRA_FULL_ERROR", "1")
warnings.filterwarnings("ignore", message=".*settotalmass.*")

import pytest
import torch

torch.set_num_threads(1)


@pytest.fixture(autouse=True)
def env_registry_as_it_was():
    """A test that imports a user's env module (``env.module``, examples/own_env.py) registers envs process-wide, and
    the module is imported once per process: every later test sees the registry and that import cache as before."""
    from umrl.envs import ENV_NAMES, unregister_env, user_envs

    envs, modules = set(ENV_NAMES), dict(user_envs._FILE_MODULES)
    yield
    for name in set(ENV_NAMES) - envs:
        unregister_env(name)
    user_envs._FILE_MODULES.clear()
    user_envs._FILE_MODULES.update(modules)


@pytest.fixture
def tiny_diayn_checkpoint(tmp_path, request):
    """A minimal point_nav DIAYN checkpoint (4 skills, a skill actor and a discriminator with one 16-unit layer each)
    in ``tmp_path / "diayn"``; returns ``(directory, discriminator)``. Parametrised indirectly, the parameter is the
    discriminator's ``input_dims`` (default ``None``: the whole observation)."""
    from umrl.checkpoints import DIAYN_FORMAT
    from umrl.checkpoints.folder import Checkpointer
    from umrl.modules.discriminator import make_discriminator
    from umrl.modules.sac import make_skill_actor

    directory = tmp_path / "diayn"
    input_dims = getattr(request, "param", None)
    discriminator = make_discriminator(2, 4, hidden=(16,), seed=0, input_dims=input_dims)
    torch.manual_seed(0)
    actor = make_skill_actor(2, 4, 2, hidden=(16,))
    meta = {"env": "point_nav", "obs_dim": 2, "act_dim": 2, "num_skills": 4, "hidden": [16],
            "discriminator_hidden": [16], "discriminator_observation_key": ["next", "observation"],
            "discriminator_input_dims": input_dims}
    DIAYN_FORMAT.save(Checkpointer(directory / "checkpoints"), 1, meta, discriminator=discriminator.state_dict(),
                      actor=actor.state_dict())
    return directory, discriminator


@pytest.fixture
def tiny_maml_run(tmp_path):
    """A one-iteration oracle MAML run on point_nav (2 tasks × 2 trajectories, horizon 10, one 16-unit layer) in
    ``tmp_path / "maml"``; returns the run directory."""
    from umrl.trainers import compose
    from umrl.trainers.maml import train

    directory = tmp_path / "maml"
    train(compose("maml", ["proposal=oracle", "iterations=1", "meta_batch_size=2", "trajectories_per_task=2",
                           "env.horizon=10", "policy.hidden=[16]", "logger.backend=none", "progress=false",
                           f"output_dir={directory}"]))
    return directory
