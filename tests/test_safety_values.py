"""Values the Python API and the configs take are checked where they enter: a non-finite float is refused by name at
construction, and a ``$WANDB_DIR`` wandb could not write is refused before a run starts (wandb would quietly write to
the system's temporary folder while umrl's summary named the other one)."""
import math

import pytest
import torch
from script_loading import compose_config
from tensordict import TensorDict

from umrl.configs import ConfigError, validate
from umrl.configs.maml import MAMLConfig
from umrl.configs.suite import SuiteConfig
from umrl.envs.tasks import goal_within
from umrl.loggers import wandb_dir
from umrl.metatest.protocol import AdaptationConfig, TaskAdapter, make_eval_env, sgd_lr_factor
from umrl.modules import make_discriminator, make_gaussian_policy, make_skill_actor, make_skill_qvalue
from umrl.modules.bnn import BayesianDynamics
from umrl.modules.stacked_mlp import StackedMLP
from umrl.objectives import DIAYNLoss
from umrl.objectives.diayn import DIAYNUpdate, make_diayn_optimizers
from umrl.objectives.stacked_diayn import StackedDIAYNLoss
from umrl.trainers import compose
from umrl.transforms.vime_bonus import VIMEBonus
from umrl.validation import InvalidValue


def diayn_loss(**kwargs) -> DIAYNLoss:
    return DIAYNLoss(make_skill_actor(2, 4, 2, hidden=(8,)), make_skill_qvalue(2, 4, 2, hidden=(8,)),
                     make_discriminator(2, 4, hidden=(8,)), num_skills=4, **kwargs)


def stacked(width: int) -> StackedMLP:
    return StackedMLP([torch.zeros(width, 3, 2)], [torch.zeros(width, 3)])


CONSTRUCTORS = {  # key -> a call with that key set to the bad value x
    "alpha_init": lambda x: diayn_loss(alpha_init=x),
    "target_entropy": lambda x: diayn_loss(target_entropy=x, fixed_alpha=False),
    "lr": lambda x: make_diayn_optimizers(diayn_loss(), lr=x, discriminator_lr=1e-3),
    "discriminator_lr": lambda x: make_diayn_optimizers(diayn_loss(), lr=1e-3, discriminator_lr=x),
    "tau": lambda x: DIAYNUpdate(loss := diayn_loss(), make_diayn_optimizers(loss, lr=1e-3, discriminator_lr=1e-3),
                                 tau=x),
    "gamma": lambda x: StackedDIAYNLoss(stacked(1), stacked(2), stacked(2), stacked(1), torch.zeros(1), num_skills=4,
                                        gamma=x),
    "init_std": lambda x: make_gaussian_policy(2, 2, hidden=[8], init_std=x),
    "prior_std": lambda x: BayesianDynamics(2, 2, prior_std=x),
    "likelihood_std": lambda x: BayesianDynamics(2, 2, likelihood_std=x),
    "eta": lambda x: VIMEBonus(BayesianDynamics(2, 2), eta=x),
    "protocol.gamma": lambda x: AdaptationConfig(gamma=x),
    "protocol.lmbda": lambda x: AdaptationConfig(lmbda=x),
    "later_factor": lambda x: sgd_lr_factor("swept", 1, x),
    "tolerance": lambda x: goal_within(x),
}


@pytest.mark.parametrize("value", [math.nan, math.inf])
@pytest.mark.parametrize("key", CONSTRUCTORS)
def test_a_non_finite_float_is_refused_by_name_at_construction(key, value):
    with pytest.raises(InvalidValue, match=rf"^{key}: got {value}; expected a finite number"):
        CONSTRUCTORS[key](value)


def test_a_task_adapters_lr_is_refused_by_name():
    env = make_eval_env("point_nav", torch.zeros(2, 2), 2, seed=0, horizon=5)
    with pytest.raises(InvalidValue, match=r"^lr: got nan; expected a finite number > 0"):
        TaskAdapter(make_gaussian_policy(2, 2, hidden=[8]), env, 2, optimizer="sgd", lr=math.nan)
    env.close()


def test_the_checks_leave_legal_values_alone():
    assert AdaptationConfig(gamma=0, lmbda=0).gamma == 0  # TD(0) one-step advantages are legal
    assert BayesianDynamics(2, 2, init_std=None).prior_std == 0.5
    assert VIMEBonus(BayesianDynamics(2, 2), eta=0).eta == 0
    update = DIAYNUpdate(loss := diayn_loss(), make_diayn_optimizers(loss, lr=1e-3, discriminator_lr=1e-3), tau=0.01)
    assert update.target_updater is not None and diayn_loss(target_entropy="auto").num_skills == 4
    success = goal_within(0.1)(TensorDict({"position": torch.zeros(1, 2)}, [1]), torch.zeros(1, 2))
    assert success.all()


def composed(name: str, overrides: list[str]):
    """The recipe's or the suite's composed config (not validated)."""
    if name == "suite":
        return compose_config("umrl/suite/config", "suite", overrides)
    return compose(name, overrides)


@pytest.mark.parametrize("where", ["afile", "afile/below"])
@pytest.mark.parametrize("name, schema", [("maml", MAMLConfig), ("suite", SuiteConfig)])
def test_a_wandb_dir_that_cannot_be_written_is_refused_before_the_run(tmp_path, monkeypatch, where, name, schema):
    (tmp_path / "afile").write_text("not a folder")
    monkeypatch.setenv("WANDB_DIR", str(tmp_path / where))
    fault = "a file" if where == "afile" else f"{tmp_path / 'afile'} is a file"
    line = rf"WANDB_DIR: got '{tmp_path / where}' \({fault}\); expected a writable directory"
    with pytest.raises(InvalidValue, match=line):
        wandb_dir()
    with pytest.raises(ConfigError, match=line):
        validate(composed(name, [f"output_dir={tmp_path / 'run'}"]), schema)
    validate(composed(name, [f"output_dir={tmp_path / 'run'}", "logger.backend=csv"]), schema)  # WANDB_DIR unread
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_a_wandb_dir_to_create_is_accepted(tmp_path, monkeypatch):
    monkeypatch.setenv("WANDB_DIR", str(tmp_path / "new" / "wandb_root"))
    assert wandb_dir() == tmp_path / "new" / "wandb_root"
