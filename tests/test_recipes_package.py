"""umrl.trainers composes a trainer's config by name with overrides, also inside a running Hydra app; the command
lines live in the package (umrl.cli), recipes/ and benchmarks/suite.py are their checkout names."""
import importlib
import runpy

import pytest
from hydra import compose as hydra_compose
from hydra.errors import ConfigCompositionException
from script_loading import REPO

import umrl.cli
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
    from umrl.suite import CONFIG_DIR as SUITE_CONFIG_DIR

    with config_dir(SUITE_CONFIG_DIR):
        assert compose("diayn").num_skills == 50  # point_nav's, from the diayn_env group
        assert "seeds" in hydra_compose("suite")  # the outer context still composes its own configs


@pytest.mark.parametrize("command", umrl.cli.COMMANDS)
def test_each_command_is_a_hydra_app_on_package_configs_with_a_checkout_script(command, monkeypatch):
    app = importlib.import_module(f"umrl.cli.{command}")
    assert callable(app.main) and (app.CONFIG_DIR / f"{app.CONFIG_NAME}.yaml").is_file()
    assert app.CONFIG_DIR.is_relative_to(CONFIG_DIR.parent)  # package data, found from a wheel too
    script = REPO / ("benchmarks/suite.py" if command == "suite" else f"recipes/{command}.py")
    calls = []
    monkeypatch.setattr(umrl.cli, "run", calls.append)
    runpy.run_path(str(script))  # imported: runs nothing
    runpy.run_path(str(script), run_name="__main__")  # run: the command's app
    assert calls == [command]
