"""umrl.configs: every yaml config matches its schema, defaults validate, and each class of bad input is one clear
error naming the key, the bad value and what is accepted (before any work starts)."""
import dataclasses
import math
import typing
import warnings

import pytest
import torch
from omegaconf import OmegaConf
from script_loading import REPO, compose_config

from umrl.checkpoints import MAML_FORMAT
from umrl.checkpoints.folder import Checkpointer
from umrl.configs import ConfigError, check_resume, resume_diff, validate
from umrl.configs.diayn import DIAYNConfig
from umrl.configs.maml import MAMLConfig
from umrl.configs.suite import SuiteConfig
from umrl.configs.validate import check_partial
from umrl.configs.vime import VIMEConfig
from umrl.envs import ENV_NAMES

RECIPES = {"diayn": DIAYNConfig, "maml": MAMLConfig, "vime": VIMEConfig}
SCHEMAS = {**RECIPES, "suite": SuiteConfig}
PROFILES = sorted(p.stem for p in (REPO / "umrl/suite/config/profile").glob("*.yaml"))


def compose(name: str, overrides=()):
    if name == "suite":
        return compose_config("umrl/suite/config", "suite", overrides)
    return compose_config("umrl/configs", name, overrides)


def schema_keys(schema: type, prefix: str = "") -> set[str]:
    hints = typing.get_type_hints(schema)
    keys = set()
    for f in dataclasses.fields(schema):
        if dataclasses.is_dataclass(hints[f.name]):
            keys |= schema_keys(hints[f.name], f"{prefix}{f.name}.")
        else:
            keys.add(f"{prefix}{f.name}")
    return keys


def yaml_keys(node, schema: type, prefix: str = "") -> set[str]:
    """Dotted keys of a yaml mapping, descending where the schema has a group (open mappings are leaves)."""
    hints = typing.get_type_hints(schema)
    keys = set()
    for key, value in node.items():
        sub = hints.get(key)
        if sub is not None and dataclasses.is_dataclass(sub) and isinstance(value, dict):
            keys |= yaml_keys(value, sub, f"{prefix}{key}.")
        else:
            keys.add(f"{prefix}{key}")
    return keys


def load_yaml(relative: str) -> dict:
    raw = OmegaConf.to_container(OmegaConf.load(REPO / relative))
    return {k: v for k, v in raw.items() if k not in ("hydra", "defaults")}


@pytest.mark.parametrize("name", list(SCHEMAS))
def test_yaml_keys_equal_schema_keys(name):
    path = "umrl/suite/config/suite.yaml" if name == "suite" else f"umrl/configs/{name}.yaml"
    assert yaml_keys(load_yaml(path), SCHEMAS[name]) == schema_keys(SCHEMAS[name])


@pytest.mark.parametrize("profile", PROFILES)
def test_profile_keys_are_schema_keys_with_valid_values(profile):
    values = load_yaml(f"umrl/suite/config/profile/{profile}.yaml")
    assert yaml_keys(values, SuiteConfig) <= schema_keys(SuiteConfig)
    assert check_partial(values, SuiteConfig) == []


@pytest.mark.parametrize("path", [*(f"umrl/configs/{name}.yaml" for name in RECIPES), "umrl/suite/config/suite.yaml"])
def test_env_lists_in_config_comments_are_the_registered_envs(path):
    """The comments beside ``env.name`` / ``envs`` list every registered env, and only those."""
    comments = [line.split("#", 1)[1] for line in (REPO / path).read_text().splitlines()
                if line.lstrip().startswith(("name:", "envs:")) and "point_nav |" in line]
    assert len(comments) == 1
    names = comments[0][comments[0].index("point_nav |"):]
    listed = [word.split()[0] for word in names.split("|")]
    assert listed == list(ENV_NAMES)


@pytest.mark.parametrize("name,overrides", [
    *[(recipe, [f"env.name={env}"]) for recipe in RECIPES for env in ("point_nav", "half_cheetah", "ant")],
    *[("suite", [f"profile={profile}"]) for profile in PROFILES],
])
def test_default_configs_validate(name, overrides):
    cfg = validate(compose(name, overrides), SCHEMAS[name])
    assert OmegaConf.is_config(cfg)
    if name != "suite":
        assert cfg.env.name in cfg.output_dir  # interpolations resolved
        assert cfg.device == "cpu"


def test_validated_config_is_typed_and_resolves_auto_device():
    cfg = validate(compose("maml", ["device=auto", "trpo.max_kl=1"]), MAMLConfig)
    assert cfg.device == ("cuda" if torch.cuda.is_available() else "cpu")
    assert isinstance(cfg.trpo.max_kl, float)
    with pytest.raises(Exception, match="iterations"):
        cfg.iterations = "abc"
    with pytest.raises(Exception, match="iteratons"):
        cfg.iteratons = 5


NO_GPU = pytest.mark.skipif(torch.cuda.is_available(), reason="device=cuda is valid with a GPU")


@pytest.mark.parametrize("name,overrides,line", [
    # silent before: ran with a default, ignored the value or did nothing
    ("diayn", ["num_skills=0"], "num_skills: got 0; expected an integer >= 2"),
    ("diayn", ["network.discriminator_input_dims=[0,2]"],
     "network.discriminator_input_dims: got [0, 2]; expected null or distinct integers < 2 (point_nav's obs_dim)"),
    pytest.param("maml", ["device=cuda"], "device: got 'cuda' (no CUDA device is available on this machine); "
                 "expected one of 'cpu', 'auto'", marks=NO_GPU),
    ("maml", ["iterations=-5"], "iterations: got -5; expected an integer >= 1"),
    ("maml", ["compile=true"], "compile: got True (torch.compile cannot differentiate a compiled graph twice"),
    ("diayn", ["optim.cudagraphs=true"], "optim.cudagraphs: got True; expected false with device=cpu"),
    ("maml", ["cudagraphs=true"], "cudagraphs: got True; expected false with device=cpu"),
    ("suite", ["+pretrain.maml.overrides.cudagraphs=true"],
     "pretrain.maml.overrides.cudagraphs: got True; expected false with device=cpu"),
    ("suite", ["+pretrain.maml.overrides.compile=true"], "pretrain.maml.overrides.compile: got True (torch.compile"),
    ("suite", ["+pretrain.diayn.overrides.optim.cudagraphs=true"],
     "pretrain.diayn.overrides.optim.cudagraphs: got True; expected false with device=cpu"),
    ("vime", ["coverage.cell_size=0"], "coverage.cell_size: got 0; expected null or a finite number > 0"),
    ("suite", ["launcher.workers=-1"], "launcher.workers: got -1; expected an integer >= 0"),
    ("maml", ["maml.inner_lr=nan"], "maml.inner_lr: got nan; expected a finite number > 0"),
    ("maml", ["proposal=diayn", "diayn_checkpoint=/no/such/run"],
     ("diayn_checkpoint: got '/no/such/run' (/no/such/run does not exist); expected an existing file or directory "
     "(a DIAYN run directory or step_*.safetensors file: proposal=diayn needs it)")),
    # obscure before: a crash far from the cause
    ("diayn", ["checkpoint.every=0"], "checkpoint.every: got 0; expected an integer >= 1"),
    ("maml", ["checkpoint.every=0"], "checkpoint.every: got 0; expected an integer >= 1"),
    ("maml", ["iterations=abc"], "iterations: got 'abc'; expected an integer >= 1"),
    ("vime", ["iterations=2.5"], "iterations: got 2.5; expected an integer >= 1"),
    ("diayn", ["optim.lr=fast"], "optim.lr: got 'fast'; expected a finite number > 0"),
    ("diayn", ["resume=maybe"], "resume: got 'maybe'; expected true or false"),
    ("suite", ["seeds=[]"], "seeds: got []; expected a non-empty list of distinct integers in [0, 9223372036854775807]"),
    ("suite", ["seeds=[0,-1]"], "seeds[1]: got -1; expected an integer in [0, 9223372036854775807]"),
    # more ranges and choices
    ("maml", ["trpo.hvp_fraction=1.5"], "trpo.hvp_fraction: got 1.5; expected a finite number in (0, 1]"),
    ("maml", ["trpo.hvp=fisher"], "trpo.hvp: got 'fisher'; expected one of 'gauss_newton', 'analytic', 'exact'"),
    ("maml", ["maml.num_inner_steps=2"], ("maml.num_inner_steps: got 2; expected 1 with trpo.hvp=gauss_newton (it "
     "differentiates one inner step; trpo.hvp=exact takes any number)")),
    ("maml", ["trpo.hvp=analytic", "maml.task_loop=true"], ("maml.task_loop: got True; expected null with "
     "trpo.hvp=analytic (it differentiates the task-batched MLP; trpo.hvp=gauss_newton takes any)")),
    ("maml", ["policy.hidden=[]"], "policy.hidden: got []; expected a non-empty list of integers >= 1"),
    ("vime", ["env.name=walker"], "env.name: got 'walker'; expected one of 'point_nav', 'half_cheetah', 'ant'"),
    # a removed env (ant's reward is now the MAML code's, which this ablation env used to carry)
    ("maml", ["env.name=ant_maml_reward"],
     "env.name: got 'ant_maml_reward'; expected one of 'point_nav', 'half_cheetah', 'ant'"),
    ("vime", ["logger.backend=tensorboard"], ("logger.backend: got 'tensorboard'; expected one of 'wandb', 'csv', "
     "'none'")),
    ("vime", ["dynamics.holdout_fraction=1"], "dynamics.holdout_fraction: got 1; expected a finite number in (0, 1)"),
    ("diayn", ["env.num_envs=16", "collector.frames_per_batch=1601"],
     "collector.frames_per_batch: got 1601; expected a multiple of env.num_envs (16)"),
    ("diayn", ["env.name=half_cheetah", "env.backend=gym", "seeds=[0,1]"],
     ("env.backend: got 'gym' (seeds=[0, 1] share gymnasium's vector env); expected default or batched with several "
      "seeds")),
    ("diayn", ["seeds=[0,1,0]"], ("seeds: got [0, 1, 0] (repeated entries); expected null or a non-empty list of "
                                  "distinct integers in [0, 9223372036854775807]")),
    ("suite", ["methods=[scratch,sac]"], ("methods[1]: got 'sac'; expected one of 'uml_diayn', 'uml_random', "
     "'oracle', 'vime_init', 'diayn_init', 'scratch'")),
    ("suite", ["++pretrain.maml.overrides.iterations=-5"],
     "pretrain.maml.overrides.iterations: got -5; expected an integer >= 1"),
    ("suite", ["+pretrain.vime.overrides.itrations=5"],
     "pretrain.vime.overrides.itrations: unexpected key; expected one of the keys of VIMEConfig"),
])
def test_bad_input_is_one_clear_error(name, overrides, line):
    with pytest.raises(ConfigError) as info:
        validate(compose(name, overrides), SCHEMAS[name])
    assert any(e.startswith(line) for e in info.value.errors), info.value.errors
    assert line.split(";")[0] in str(info.value)


def test_report_steps_beyond_k_are_left_out_with_a_warning_not_refused():
    """report.steps lists columns wanted; with a smaller K (protocol.num_steps) the table keeps those within K and a
    warning names the key, the steps left out and K."""
    with pytest.warns(UserWarning, match=r"report.steps: got \[0, 1, 5\] \(\[5\] left out: K = protocol.num_steps = 3\); "
                                         r"expected steps <= protocol.num_steps \(3\) to show each in the table"):
        validate(compose("suite", ["protocol.num_steps=3"]), SuiteConfig)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        validate(compose("suite", ["protocol.num_steps=5"]), SuiteConfig)  # 5 = K: a column


def test_missing_reuse_path_is_refused_before_any_work(tmp_path):
    template = str(tmp_path / "maml_{proposal}" / "seed{seed}")
    cfg = compose("suite", ["profile=quick", f"pretrain.maml.reuse='{template}'"])
    with pytest.raises(ConfigError) as info:
        validate(cfg, SuiteConfig)
    run = tmp_path / "maml_diayn" / "seed0"
    assert (f"pretrain.maml.reuse: got '{template}' (env=point_nav seed=0: {run} has no checkpoint); "
            "expected a finished run directory holding checkpoints/step_*.safetensors") in info.value.errors
    for proposal in ("diayn", "random", "oracle"):  # a run with a checkpoint of the method is accepted
        meta = {**dict.fromkeys(MAML_FORMAT.meta_keys, 1), "env": "point_nav", "proposal": proposal, "obs_dim": 2}
        MAML_FORMAT.save(Checkpointer(tmp_path / f"maml_{proposal}" / "seed0" / "checkpoints"), 20, meta)
    validate(cfg, SuiteConfig)


def test_every_bad_key_is_listed_in_one_error():
    overrides = ["iterations=-5", "seed=abc", "trpo.max_kl=0", "env.name=mars", "+itrations=3"]
    with pytest.raises(ConfigError) as info:
        validate(compose("maml", overrides), MAMLConfig)
    keys = sorted(e.split(":")[0] for e in info.value.errors)
    assert keys == ["env.name", "iterations", "itrations", "seed", "trpo.max_kl"]
    assert str(info.value).startswith("invalid config (MAMLConfig, 5 errors):")


def test_missing_and_unreadable_keys_are_named():
    values = OmegaConf.to_container(compose("vime"))
    del values["trpo"]["cg_iters"]
    values["output_dir"] = "${nowhere}"
    with pytest.raises(ConfigError) as info:
        validate(values, VIMEConfig)
    assert "trpo.cg_iters: missing; TRPOConfig requires it" in info.value.errors
    assert any(e.startswith("output_dir: cannot be read (InterpolationKeyError") for e in info.value.errors)


def test_resume_diff_lists_changed_keys_except_the_allow_list(tmp_path):
    saved = validate(compose("maml"), MAMLConfig)
    same = validate(compose("maml", ["iterations=1000", "logger.backend=csv", "progress=false", "resume=true",
                                     "checkpoint.every=3", f"output_dir={tmp_path / 'elsewhere'}"]), MAMLConfig)
    assert resume_diff(saved, same) == {}
    check_resume(saved, same)
    changed = validate(compose("maml", ["seed=5", "trpo.max_kl=0.5", "policy.hidden=[64,64]", "proposal=random",
                                        "num_skills=7", "env.name=half_cheetah"]), MAMLConfig)
    diff = resume_diff(OmegaConf.to_container(saved), changed)
    assert diff == {"seed": (0, 5), "trpo.max_kl": (0.01, 0.5), "policy.hidden": ([300, 300], [64, 64]),
                    "proposal": ("oracle", "random"), "num_skills": (None, 7), "env.name": ("point_nav", "half_cheetah"),
                    "default_num_skills": (50, 20), "discriminator_hidden": ([32, 32], [300, 300]),
                    "diayn_checkpoint": ("outputs/diayn/point_nav/seed0", "outputs/diayn/half_cheetah/seed5")}
    with pytest.raises(ConfigError, match=r"trpo\.max_kl: checkpoint has 0\.01, this run has 0\.5"):
        check_resume(saved, changed)


def test_runs_saved_before_a_key_was_added_resume_with_its_old_behaviour():
    saved = OmegaConf.to_container(validate(compose("diayn"), DIAYNConfig))
    del saved["network"]["discriminator_input_dims"]  # a checkpoint written before the key existed
    assert resume_diff(saved, validate(compose("diayn"), DIAYNConfig)) == {}
    prior = validate(compose("diayn", ["network.discriminator_input_dims=[0]"]), DIAYNConfig)
    assert resume_diff(saved, prior) == {"network.discriminator_input_dims": ("<absent>", [0])}


def test_resume_diff_marks_keys_present_on_one_side():
    assert resume_diff({"a": 1, "b": {"c": 2}}, {"a": 1}, allow=()) == {"b.c": (2, "<absent>")}
    assert resume_diff({"a": 1}, {"a": 1, "d": math.pi}, allow=("d",)) == {}
