"""Env-dependent defaults follow the reference code: DIAYN's episode length and budget, MAML's iterations."""
import pytest
from omegaconf import OmegaConf
from script_loading import compose_config

from umrl.configs import validate
from umrl.configs.diayn import DIAYNConfig
from umrl.configs.maml import MAMLConfig


def recipe(name, overrides=()):
    return compose_config("umrl/configs", name, overrides)


@pytest.mark.parametrize("env, horizon, frames", [("point_nav", 100, 50_000), ("half_cheetah", 1000, 10_000_000),
                                                  ("ant", 1000, 10_000_000)])
def test_diayn_episode_and_budget_are_the_references(env, horizon, frames):
    cfg = validate(recipe("diayn", [f"env.name={env}"]), DIAYNConfig)
    assert (cfg.env.horizon, cfg.collector.total_frames) == (horizon, frames)
    # one env, one step then one update: the reference's sampler and n_train_repeat=1
    assert cfg.env.num_envs == cfg.collector.frames_per_batch == 1
    assert DIAYNConfig.notices(OmegaConf.to_container(cfg)) == []  # the default budget is not warned about
    assert (cfg.optim.lr, cfg.replay_buffer.batch_size, cfg.optim.updates_per_frame) == (3e-4, 128, 1.0)


def test_explicit_values_win_over_the_env_defaults():
    cfg = validate(recipe("diayn", ["env.name=ant", "env.horizon=100", "collector.total_frames=200000",
                                    "collector.frames_per_batch=3200"]), DIAYNConfig)
    assert (cfg.env.horizon, cfg.collector.total_frames, cfg.collector.frames_per_batch) == (100, 200_000, 3200)


@pytest.mark.parametrize("env, iterations", [("point_nav", 100), ("half_cheetah", 475), ("ant", 375)])
def test_maml_iterations_are_the_references(env, iterations):
    assert validate(recipe("maml", [f"env.name={env}"]), MAMLConfig).iterations == iterations
    assert validate(recipe("maml", [f"env.name={env}", "iterations=7"]), MAMLConfig).iterations == 7


def test_meta_test_defaults_to_the_reference_schedule():
    suite = compose_config("benchmarks/config", "suite", [])
    assert suite.protocol.sgd_schedule == "reference"
