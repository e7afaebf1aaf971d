"""umrl.trainers composes a trainer's config by name with overrides, also inside a running Hydra app; recipes/ holds
the command lines."""
import pytest
from hydra import compose as hydra_compose
from hydra.errors import ConfigCompositionException
from script_loading import load_script

import umrl.trainers
from umrl.trainers import CONFIG_DIR, compose, config_dir


def test_compose_applies_overrides_and_rejects_unknown_keys_and_names():
    cfg = compose("maml", ["proposal=random", "env.horizon=7"])
    assert cfg.proposal == "random" and cfg.env.horizon == 7 and cfg.output_dir.endswith("random/seed0")
    with pytest.raises(ConfigCompositionException, match="no_such_key"):
        compose("vime", ["no_such_key=1"])
    with pytest.raises(ValueError, match="unknown recipe 'sac'; valid choices"):
        umrl.trainers.train("sac")


def test_compose_inside_another_hydra_context_restores_it():
    with config_dir(CONFIG_DIR.parents[1] / "benchmarks" / "config"):
        assert compose("diayn").num_skills is None
        assert "seeds" in hydra_compose("suite")  # the outer context still composes its own configs


@pytest.mark.parametrize("name", umrl.trainers.TRAINERS)
def test_each_recipe_module_has_train_and_main(name):
    import importlib

    module = importlib.import_module(f"umrl.trainers.{name}")
    script = load_script(f"recipes/{name}.py")  # the command line: a Hydra main over the trainer
    assert callable(module.train) and callable(script.main)
