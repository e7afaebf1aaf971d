"""One config system: each recipe's per-env defaults are a Hydra group chosen from env.name, the composed config
holds the values a run uses, and EnvSpec keeps physics and task facts only."""
import dataclasses

import pytest
from omegaconf import OmegaConf

from umrl.configs import resume_diff, validate
from umrl.configs.diayn import DIAYNConfig
from umrl.configs.env_groups import (
    CONFIG_DIR,
    ENV_GROUPS,
    GENERIC,
    env_defaults,
    with_env_group,
    with_env_group_argv,
)
from umrl.envs import ENV_NAMES, EnvSpec
from umrl.envs.gym_cmp import gym_env_spec
from umrl.trainers import compose

BUILTIN = ("point_nav", "half_cheetah", "ant")


def _keys(node, prefix=""):
    for key, value in node.items():
        if isinstance(value, dict):
            yield from _keys(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}"


@pytest.mark.parametrize("recipe", sorted(ENV_GROUPS))
def test_every_builtin_env_has_a_complete_group_file(recipe):
    """Each built-in env's file sets its env.name and every key the generic file sets, so no env falls back on
    another env's value; the recipe's yaml leaves those keys to the group (???)."""
    generic = set(_keys(env_defaults(recipe, "gym:Unknown-v0")))
    for env in BUILTIN:
        values = env_defaults(recipe, env)
        assert values["env"]["name"] == env
        assert set(_keys(values)) - {"env.name"} == generic, env
    assert set(ENV_NAMES) >= set(BUILTIN)
    primary = OmegaConf.load(CONFIG_DIR / f"{recipe}.yaml")
    for key in generic:
        parent, _, name = key.rpartition(".")
        node = OmegaConf.select(primary, parent) if parent else primary
        assert OmegaConf.is_missing(node, name), f"{recipe}.yaml sets {key}: the group's value would be hidden"


def test_env_name_chooses_the_group():
    assert with_env_group("diayn", ["env.name=ant", "seed=3"]) == ["env.name=ant", "seed=3", "diayn_env=ant"]
    assert with_env_group("maml", ["env.name=gym:Hopper-v5"]) == ["env.name=gym:Hopper-v5", f"maml_env={GENERIC}"]
    assert with_env_group("maml", ["env.name=ant", "maml_env=point_nav"]) == ["env.name=ant", "maml_env=point_nav"]
    assert with_env_group("diayn", ["seed=3"]) == ["seed=3"]
    assert with_env_group("vime", ["env.name=ant"]) == ["env.name=ant"]  # no env-dependent defaults
    # a sweep over built-in envs sweeps the group, whose files set env.name: one job per env, not a product
    assert with_env_group("diayn", ["env.name=point_nav,ant", "seed=0"]) == ["diayn_env=point_nav,ant", "seed=0"]
    with pytest.raises(ValueError, match=r"env.name=point_nav,gym:Hopper-v5: a sweep of env.name over built-in envs "
                                         r"and others; run one command for the built-in envs \(point_nav\)"):
        with_env_group("diayn", ["env.name=point_nav,gym:Hopper-v5"])
    assert with_env_group_argv("maml", ["-m", "env.name=ant", "--cfg", "job"]) == [
        "-m", "--cfg", "job", "env.name=ant", "maml_env=ant"]
    assert with_env_group_argv("maml", ["--cfg", "job", "seed=1"]) == ["--cfg", "job", "seed=1"]


@pytest.mark.parametrize("recipe, key, values", [
    ("diayn", "env.horizon", {"point_nav": 100, "half_cheetah": 1000, "ant": 1000}),
    ("diayn", "num_skills", {"point_nav": 50, "half_cheetah": 20, "ant": 20}),
    ("diayn", "collector.total_frames", {"point_nav": 50_000, "half_cheetah": 10_000_000, "ant": 10_000_000}),
    ("maml", "iterations", {"point_nav": 100, "half_cheetah": 475, "ant": 375}),
    ("maml", "discriminator_hidden", {"point_nav": [32, 32], "half_cheetah": [300, 300], "ant": [300, 300]}),
])
def test_the_composed_config_holds_the_env_values(recipe, key, values):
    """What --cfg job prints is what runs: the values are in the composed config, before any validation; an
    explicit value wins."""
    for env, value in values.items():
        assert OmegaConf.select(compose(recipe, [f"env.name={env}"]), key) == value
    assert OmegaConf.select(compose(recipe, ["env.name=ant", f"{key}=7"]), key) == 7


def test_env_spec_keeps_physics_and_task_facts_only():
    fields = {f.name for f in dataclasses.fields(EnvSpec)}
    assert not fields & {"num_skills", "diayn_horizon", "diayn_frames", "diayn_hidden", "maml_iterations"}
    with pytest.raises(ValueError, match=r"num_skills: got 10; expected no such argument: a recipe setting, given "
                                         r"on the command line .*num_skills=10 for DIAYN"):
        gym_env_spec("Hopper-v5", None, {}, num_skills=10)


def test_a_run_saved_before_the_groups_resumes():
    """A checkpoint's config from before: DIAYN's skill count saved as null, MAML's new keys absent."""
    cfg = OmegaConf.to_container(validate(compose("diayn", ["env.name=ant"]), DIAYNConfig))
    assert resume_diff({**cfg, "num_skills": None}, cfg) == {}  # null meant ant's 20
    assert resume_diff({**cfg, "num_skills": None}, {**cfg, "num_skills": 7}) == {"num_skills": (None, 7)}
    assert resume_diff({**cfg, "num_skills": 20}, {**cfg, "num_skills": 7}) == {"num_skills": (20, 7)}
    maml = OmegaConf.to_container(compose("maml", ["proposal=random"]), resolve=True)
    saved = {k: v for k, v in maml.items() if k not in ("default_num_skills", "discriminator_hidden")}
    assert resume_diff(saved, maml) == {}
    assert resume_diff(saved, {**maml, "discriminator_hidden": [8]}) == {"discriminator_hidden": ("<absent>", [8])}
