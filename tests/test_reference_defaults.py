"""Env-dependent defaults follow the reference code: DIAYN's episode length, budget and network widths, MAML's
iterations and batch sampler; every method's random init is the same draw for a seed."""
import pytest
import torch
from omegaconf import OmegaConf
from script_loading import compose_config

from umrl.configs import validate
from umrl.configs.diayn import DIAYNConfig
from umrl.configs.maml import MAMLConfig
from umrl.trainers.diayn import train as train_diayn
from umrl.trainers.maml import build


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


@pytest.mark.parametrize("env, width", [("point_nav", 32), ("half_cheetah", 300), ("ant", 300)])
def test_diayn_networks_are_the_references_layer_size(env, width):
    """``layer_size`` of mujoco_all_diayn.py (32 for its point env) sizes actor, Q-networks and discriminator, and
    UML-random's discriminator (DIAYN's, at its random init); explicit widths win."""
    cfg = validate(recipe("diayn", [f"env.name={env}"]), DIAYNConfig)
    assert cfg.network.hidden == cfg.network.discriminator_hidden == [width, width]
    cfg = validate(recipe("diayn", [f"env.name={env}", "network.hidden=[64]"]), DIAYNConfig)
    assert (cfg.network.hidden, cfg.network.discriminator_hidden) == ([64], [width, width])
    maml = validate(recipe("maml", [f"env.name={env}", "proposal=random"]), MAMLConfig)
    assert maml.discriminator_hidden == [width, width] and maml.default_num_skills == cfg.num_skills
    if env == "point_nav":  # one cheap env is enough for the proposal's widths
        random, _, _, _ = build(maml)
        widths = [m.out_features for m in random.env.transform[-1].modules() if isinstance(m, torch.nn.Linear)]
        assert widths[:-1] == [width, width]
        random.env.close()


def test_every_methods_random_init_is_the_same_draw_for_a_seed(tmp_path):
    """MAML's init for every proposal, VIME's and scratch's: whatever the proposal drew first (a DIAYN checkpoint's
    loading, a random discriminator)."""
    from umrl.metatest.methods import load_initialisation

    train_diayn(compose_config("umrl/configs", "diayn", [
        "+profile=diayn_tiny", "collector.total_frames=160", "collector.frames_per_batch=80",
        "collector.init_random_frames=80", "replay_buffer.batch_size=16", "eval.every=160", "checkpoint.every=160",
        f"output_dir={tmp_path / 'diayn'}", "logger.backend=none", "progress=false"]))
    scratch = load_initialisation("scratch", "point_nav", None, seed=3).policy.state_dict()
    for proposal in ("oracle", "random", "diayn"):
        cfg = validate(recipe("maml", [f"proposal={proposal}", "seed=3", f"diayn_checkpoint={tmp_path / 'diayn'}",
                                       "logger.backend=none"]), MAMLConfig)
        torch.manual_seed(123)  # the global RNG's state does not matter
        _, policy, _, _ = build(cfg)
        for key, value in scratch.items():
            torch.testing.assert_close(policy.state_dict()[key], value, rtol=0, atol=0, msg=f"{proposal}: {key}")


@pytest.mark.parametrize("env, iterations", [("point_nav", 100), ("half_cheetah", 475), ("ant", 375)])
def test_maml_iterations_are_the_references(env, iterations):
    assert validate(recipe("maml", [f"env.name={env}"]), MAMLConfig).iterations == iterations
    assert validate(recipe("maml", [f"env.name={env}", "iterations=7"]), MAMLConfig).iterations == 7


def test_meta_test_defaults_to_the_reference_schedule():
    suite = compose_config("umrl/suite/config", "suite", [])
    assert suite.protocol.sgd_schedule == "reference"
