"""The suite runs a user's env: ``env_module`` is imported before ``envs`` is checked and by every job (pre-training,
meta-training, meta-test cells), in local workers as in Ray tasks (test_ray_env.py)."""
import json
import json.decoder
from pathlib import Path

import pytest
from script_loading import compose_config

from umrl.configs import ConfigError, validate
from umrl.configs.suite import SuiteConfig
from umrl.envs.user_envs import env_module_source
from umrl.metatest import read_rows
from umrl.suite import code_version, plan, run_suite

ENV_MODULE = Path(__file__).resolve().parent / "pendulum_env.py"
ENV = "gym:InvertedPendulum-v5"
TINY = ["profile=tiny", "num_tasks=2", "protocol.num_steps=1", "protocol.num_trajectories=2", "protocol.horizon=10",
        "report.steps=[0]", "logger.backend=none", "ablation.enabled=false", "launcher.workers=1",
        "pretrain.maml.overrides.iterations=1", "+pretrain.maml.overrides.env.horizon=10",
        "pretrain.diayn.overrides.collector={total_frames: 320, frames_per_batch: 160, init_random_frames: 160}",
        "pretrain.diayn.overrides.checkpoint.every=320", "pretrain.diayn.overrides.eval.every=320"]


def test_an_unregistered_env_is_refused_and_env_module_registers_it(tmp_path):
    with pytest.raises(ConfigError, match=rf"envs\[0\]: got '{ENV}'"):
        validate(compose_config("umrl/suite/config", "suite", [f"output_dir={tmp_path}", f"envs=[{ENV}]"]),
                 SuiteConfig)
    cfg = validate(compose_config("umrl/suite/config", "suite", [f"output_dir={tmp_path}", f"envs=[{ENV}]",
                                                                  f"env_module={ENV_MODULE}"]), SuiteConfig)
    assert list(cfg.envs) == [ENV]


@pytest.mark.slow
def test_the_suite_pretrains_meta_trains_and_meta_tests_a_users_env_in_worker_processes(tmp_path):
    cfg = validate(compose_config("umrl/suite/config", "suite", [
        f"output_dir={tmp_path}", *TINY, f"envs=[{ENV}]", "methods=[uml_diayn,scratch]",
        f"env_module={ENV_MODULE}"]), SuiteConfig)
    run_suite(cfg, log=lambda _: None)
    rows = read_rows([tmp_path / "results.csv"])
    assert {(row["env"], row["method"]) for row in rows} == {(ENV, "uml_diayn"), (ENV, "scratch")}
    assert [p.parent.name for p in (tmp_path / "pretrain").glob("*/*/*")] == [ENV, ENV]  # diayn, maml_diayn


def test_each_seed_of_a_gymnasium_env_gets_its_own_diayn_program(tmp_path):
    cfg = validate(compose_config("umrl/suite/config", "suite", [
        f"output_dir={tmp_path}", *TINY, f"envs=[{ENV}]", "methods=[diayn_init]", "seeds=[0,1]", "pretrain_seeds=null",
        f"env_module={ENV_MODULE}"]), SuiteConfig)
    jobs = [job for job in plan(cfg, group="g", code="code") if job.key.startswith("pretrain/")]
    assert [job.key for job in jobs] == [f"pretrain/diayn/{ENV}/seed0", f"pretrain/diayn/{ENV}/seed1"]
    assert [[a for a in job.args[1] if a.startswith("seeds=")] for job in jobs] == [["seeds=[0]"], ["seeds=[1]"]]


def test_the_code_version_covers_the_users_env_module(tmp_path):
    module = tmp_path / "my_env.py"
    module.write_text(ENV_MODULE.read_text())
    plain, with_module = code_version(), code_version(str(module))
    assert with_module != plain
    module.write_text(ENV_MODULE.read_text() + "\n# a changed reward would change every result on this env\n")
    assert code_version(str(module)) not in (plain, with_module)
    assert env_module_source("json") == Path(json.__file__).parent  # a package: its folder
    assert env_module_source("json.decoder") == Path(json.decoder.__file__)
    with pytest.raises(ValueError, match="env_module: got .no_such_module_here."):
        env_module_source("no_such_module_here")
