"""Names are names: run and profile names without path parts, reuse templates with plain fields only, reused runs of
the method's recipe, env, proposal and skill count; all refused before any work, in the house format."""
import pytest
from script_loading import compose_config

import umrl.trainers
from umrl.checkpoints import DIAYN_FORMAT, MAML_FORMAT
from umrl.checkpoints.folder import Checkpointer
from umrl.configs import ConfigError, validate
from umrl.configs.diayn import DIAYNConfig
from umrl.configs.suite import SuiteConfig
from umrl.envs import get_env_spec
from umrl.loggers import make_logger
from umrl.modules.policy import make_gaussian_policy

TINY = ["num_tasks=2", "protocol.num_steps=1", "protocol.num_trajectories=2", "protocol.horizon=10", "report.steps=[0]",
        "logger.backend=none", "ablation.enabled=false", "seeds=[0]"]


def _suite(tmp_path, *overrides):
    return validate(compose_config("umrl/suite/config", "suite", [f"output_dir={tmp_path}", *TINY, *overrides]),
                    SuiteConfig)


@pytest.mark.parametrize("bad", ["../../x", "a/b", "..", "a\\b"])
def test_run_names_are_refused_with_path_parts(tmp_path, bad):
    cfg = umrl.trainers.compose("diayn", [f"output_dir={tmp_path}", f"logger.exp_name='{bad}'"])
    with pytest.raises(ConfigError, match=r"logger.exp_name: got .*; expected a name without path separators"):
        validate(cfg, DIAYNConfig)
    with pytest.raises(ValueError, match="logger.exp_name: got"):
        make_logger({"backend": "csv"}, exp_name=bad, log_dir=tmp_path / "run")
    assert not any(tmp_path.iterdir())


def test_profile_name_is_a_name(tmp_path):
    with pytest.raises(ConfigError, match=r"profile_name: got '\.\./\.\./\.\./x'; expected a name"):
        _suite(tmp_path, "profile_name='../../../x'", "methods=[scratch]")


@pytest.mark.parametrize("template", ["{seed.__class__.__mro__}", "{seed[0]}", "{env!r}", "{seed:>99}", "{other}"])
def test_reuse_templates_hold_plain_fields_only(tmp_path, template):
    with pytest.raises(ConfigError, match=r"pretrain.diayn.reuse: got .*refused fields.*expected a path template"):
        _suite(tmp_path, "methods=[diayn_init]", f"pretrain.diayn.reuse='runs/{template}'")


def _maml_run(directory, env="point_nav", proposal="oracle", num_skills=20):
    """A MAML checkpoint of ``env``/``proposal`` whose metadata describes its (tiny) policy, as a reader checks."""
    spec = get_env_spec(env)
    meta = {**dict.fromkeys(MAML_FORMAT.meta_keys, 1), "env": env, "proposal": proposal, "num_skills": num_skills,
            "obs_dim": spec.obs_dim, "act_dim": spec.act_dim, "hidden": [4], "init_std": 1.0, "inner_lr": 0.1}
    policy = make_gaussian_policy(spec.obs_dim, spec.act_dim, hidden=[4])
    MAML_FORMAT.save(Checkpointer(directory / "checkpoints"), 5, meta, {"seed": 0}, policy=policy.state_dict())


def test_a_reused_run_must_be_of_the_methods_proposal_env_and_skills(tmp_path):
    _maml_run(tmp_path / "oracle", proposal="oracle")
    with pytest.raises(ConfigError, match=r"(?s)pretrain.diayn.reuse: .*is not a DIAYN checkpoint.*pretrain.maml.reuse: "
                                          r".*holds \{'env': 'point_nav', 'proposal': 'oracle'\}\); expected a "
                                          r"maml_diayn run with \{'env': 'point_nav', 'proposal': 'diayn'\}"):
        _suite(tmp_path / "out", "methods=[uml_diayn]", f"pretrain.maml.reuse='{tmp_path}/oracle'",
               f"pretrain.diayn.reuse='{tmp_path}/oracle'")
    _maml_run(tmp_path / "uml", proposal="diayn", num_skills=20)
    DIAYN_FORMAT.save(Checkpointer(tmp_path / "diayn" / "checkpoints"), 5,
                      {**dict.fromkeys(DIAYN_FORMAT.meta_keys), "env": "point_nav", "num_skills": 50, "obs_dim": 2}, {"seed": 0})
    with pytest.raises(ConfigError, match=r"meta-trained on 20 skills\); expected a UML-DIAYN run on the reused DIAYN run's 50 skills"):
        _suite(tmp_path / "out", "methods=[uml_diayn]", f"pretrain.maml.reuse='{tmp_path}/uml'",
               f"pretrain.diayn.reuse='{tmp_path}/diayn'")
    _maml_run(tmp_path / "cheetah", env="half_cheetah", proposal="random")
    with pytest.raises(ConfigError, match=r"holds \{'env': 'half_cheetah'"):
        _suite(tmp_path / "out", "methods=[uml_random]", f"pretrain.maml.reuse='{tmp_path}/cheetah'")
    _maml_run(tmp_path / "random", proposal="random")
    _suite(tmp_path / "out", "methods=[uml_random]", f"pretrain.maml.reuse='{tmp_path}/random'")
