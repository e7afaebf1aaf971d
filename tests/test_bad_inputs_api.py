"""Python API arguments that used to fail deep inside TorchRL, torch or an env are refused at entry naming the argument
(``<arg>: got <value>; expected <what is accepted>``), or handled: GAE with ``gamma=0`` / ``lmbda=0``."""
import re

import pytest
import torch
from tensordict import TensorDict

from umrl.envs import make_env, make_task_env
from umrl.modules import make_discriminator, make_gaussian_policy, make_skill_actor, make_skill_qvalue
from umrl.modules.policy import policy_log_std
from umrl.objectives import DIAYNLoss, ImportanceSamplingLoss, MAMLLoss
from umrl.objectives.policy_gradient import compute_advantages
from umrl.proposals import make_proposal
from umrl.rollout import NonFiniteActions, collect, collect_env_steps
from umrl.trainers import MAMLTrainer, VIMETrainer, compose
from umrl.transforms.discriminator_reward import DiscriminatorReward
from umrl.transforms.skill import SkillTransform
from umrl.validation import InvalidType, InvalidValue

no_cuda = pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine without CUDA")

MAML_TINY = ["proposal=oracle", "env.horizon=8", "meta_batch_size=2", "trajectories_per_task=2", "policy.hidden=[8]",
             "logger.backend=none", "progress=false", "trpo.cg_iters=3", "iterations=1"]
VIME_TINY = ["env.num_envs=4", "env.horizon=10", "policy.hidden=[8]", "dynamics.hidden=[8]",
             "dynamics.updates_per_iteration=2", "dynamics.batch_size=8", "logger.backend=none", "progress=false",
             "iterations=1"]


def _trajectories(T=2, N=3, H=5, seed=0):
    g = torch.Generator().manual_seed(seed)
    done = torch.zeros(T, N, H, 1, dtype=torch.bool)
    done[..., -1, :] = True
    done[0, 0, 2] = True  # an episode ending early: the steps after it are masked
    return TensorDict({
        "observation": torch.randn(T, N, H, 2, generator=g),
        "step_count": torch.arange(H).expand(T, N, H).unsqueeze(-1).clone(),
        "next": {"reward": torch.randn(T, N, H, 1, generator=g), "done": done},
    }, [T, N, H])


def _next_values(values):
    return torch.cat([values[..., 1:, :], torch.zeros_like(values[..., :1, :])], dim=-2)


# gamma = 0 / lmbda = 0: legal values that TorchRL's fast GAE failed on (IndexError: tuple index out of range)

@pytest.mark.parametrize("lmbda", [0.0, 0.95, 1.0])
def test_gamma_zero_advantage_is_the_reward_minus_the_baseline(lmbda):
    td = compute_advantages(_trajectories(), gamma=0.0, lmbda=lmbda, normalize=False)
    valid = td["mask"].unsqueeze(-1)
    torch.testing.assert_close(td["value_target"], td["next", "reward"] * valid)
    torch.testing.assert_close(td["advantage"], (td["next", "reward"] - td["state_value"]) * valid)


def test_lambda_zero_advantage_is_the_one_step_td_error():
    td = compute_advantages(_trajectories(), gamma=0.9, lmbda=0.0, normalize=False)
    valid = td["mask"].unsqueeze(-1)
    values, reward, ends = td["state_value"], td["next", "reward"] * valid, td["next", "done"] | ~valid
    expected = (reward + 0.9 * _next_values(values) * ~ends - values) * valid
    torch.testing.assert_close(td["advantage"], expected)


@pytest.mark.parametrize("make_loss", [MAMLLoss, ImportanceSamplingLoss], ids=["maml", "vime"])
def test_the_losses_value_estimators_take_gamma_and_lambda_zero(make_loss):
    proposal = make_proposal("oracle", "point_nav", num_tasks=2, trajectories_per_task=2, horizon=5)
    policy = make_gaussian_policy(2, 2, hidden=[8])
    batch = collect(proposal.env, policy, num_tasks=2, horizon=5)
    loss = make_loss(policy).make_value_estimator(gamma=0.0, lmbda=0.0, normalize=False)
    td = loss.value_estimator(batch)
    valid = td["mask"].unsqueeze(-1)
    torch.testing.assert_close(td["advantage"], (td["next", "reward"] - td["state_value"]) * valid)


def test_maml_and_vime_train_with_gamma_and_lambda_zero(tmp_path):
    MAMLTrainer(compose("maml", [*MAML_TINY, "advantage.gamma=0", "advantage.lmbda=0",
                                 f"output_dir={tmp_path / 'maml'}"])).step()
    VIMETrainer(compose("vime", [*VIME_TINY, "advantage.gamma=0", "advantage.lmbda=0",
                                 f"output_dir={tmp_path / 'vime'}"])).step()


# non-finite actions: blamed on what produced them, not on the env or the reward transform

def test_collect_refuses_parameters_whose_actions_are_not_finite():
    env = make_env("point_nav", 4, horizon=3)
    policy = make_gaussian_policy(2, 2, hidden=[8])
    theta = TensorDict.from_module(policy)
    log_std = next(key for key, value in theta.items(True, True) if value is policy_log_std(policy))
    params = theta.detach().expand(2).clone()
    params.get(log_std)[0] = 1e30  # task 0's std overflows
    with pytest.raises(NonFiniteActions, match=r"^params: got a TensorDict of batch size \[2\] \(12 of 24 action "
                                               r"entries are not finite\); expected parameters under which"):
        collect(env, policy, num_tasks=2, horizon=3, params=params)
    with torch.no_grad():
        policy_log_std(policy).fill_(float("nan"))
    with pytest.raises(NonFiniteActions, match=r"^policy: got a ProbabilisticActor \(24 of 24 action entries"):
        collect(env, policy, num_tasks=2, horizon=3)


def test_a_diverging_maml_inner_step_names_the_inner_learning_rate(tmp_path):
    trainer = MAMLTrainer(compose("maml", [*MAML_TINY, "maml.inner_lr=1e30", f"output_dir={tmp_path}"]))
    with pytest.raises(InvalidValue, match=r"^maml.inner_lr: got 1e\+30 \(the adapted policy's actions after the "
                                           r"inner step: \d+ of \d+ action entries are not finite\); expected a "
                                           r"smaller finite number > 0"):
        trainer.step()


# collect / collect_env_steps

@pytest.fixture
def env():
    return make_env("point_nav", 4, horizon=5)


@pytest.mark.parametrize("collector", [collect, collect_env_steps])
def test_collect_refuses_a_missing_policy(env, collector):
    extra = {"env_steps": 5} if collector is collect_env_steps else {}
    with pytest.raises(InvalidType, match=r"^policy: got None; expected a ProbabilisticActor"):
        collector(env, None, num_tasks=2, horizon=5, **extra)


def test_collect_refuses_a_missing_env():
    with pytest.raises(InvalidType, match=r"^env: got None; expected a TorchRL env"):
        collect(None, make_gaussian_policy(2, 2, hidden=[8]), num_tasks=1, horizon=5)


@pytest.mark.parametrize("horizon", [0, -1])
def test_collect_refuses_a_horizon_below_one(env, horizon):
    with pytest.raises(InvalidValue, match=rf"^horizon: got {horizon}; expected an integer >= 1"):
        collect(env, make_gaussian_policy(2, 2, hidden=[8]), num_tasks=2, horizon=horizon)


def test_collect_refuses_a_task_count_that_does_not_divide_the_env_batch(env):
    with pytest.raises(InvalidValue, match=r"^num_tasks: got 3; expected a divisor of the env's 4 copies"):
        collect(env, make_gaussian_policy(2, 2, hidden=[8]), num_tasks=3, horizon=5)


def test_collect_refuses_a_policy_of_another_observation_width(env):
    with pytest.raises(InvalidValue, match=r"^policy: got a ProbabilisticActor \(its first layer reads 3 features\); "
                                           r"expected a policy whose first layer reads the env's 2 features "
                                           r"\(observation 2\)"):
        collect(env, make_gaussian_policy(3, 2, hidden=[8]), num_tasks=2, horizon=5)


def test_collect_refuses_a_policy_that_leaves_out_the_skill_width():
    env = make_env("point_nav", 4, horizon=5).append_transform(SkillTransform(3))
    policy = make_gaussian_policy(2, 2, hidden=[8], in_keys=("observation", "skill"))
    with pytest.raises(InvalidValue, match=r"first layer reads 2 features\); expected a policy whose first layer "
                                           r"reads the env's 5 features \(observation 2 \+ skill 3\)"):
        collect(env, policy, num_tasks=2, horizon=5)
    collect(env, make_gaussian_policy(5, 2, hidden=[8], in_keys=("observation", "skill")), num_tasks=2, horizon=5)


def test_collect_refuses_a_policy_reading_a_key_the_env_does_not_write(env):
    policy = make_gaussian_policy(5, 2, hidden=[8], in_keys=("observation", "skill"))
    with pytest.raises(InvalidValue, match=r"^policy: got a ProbabilisticActor \(it reads \['skill'\], which the env "
                                           r"does not write\); expected a policy reading keys the env writes"):
        collect(env, policy, num_tasks=2, horizon=5)


def test_collect_refuses_a_policy_with_another_action_width(env):
    with pytest.raises(InvalidValue, match=r"\(its mean has 3 action dims\); expected a policy with the env's 2 "
                                           r"action dims"):
        collect(env, make_gaussian_policy(2, 3, hidden=[8]), num_tasks=2, horizon=5)


# envs: tasks and devices

def test_make_task_env_refuses_a_single_task_where_a_batch_is_expected():
    with pytest.raises(InvalidValue, match=r"^tasks: got \[0.1, 0.2\] \(shape \[2\]\); expected a \[num_envs, 2\] "
                                           r"tensor \(one point_nav task of 2 numbers per env copy\)"):
        make_task_env("point_nav", [0.1, 0.2])
    assert make_task_env("point_nav", [[0.1, 0.2]]).batch_size == (1,)  # nested lists are a batch


@pytest.mark.parametrize("tasks, error", [(None, InvalidType), (["a", "b"], InvalidType),
                                          (torch.zeros(2, 2), InvalidValue)])
def test_set_tasks_names_the_tasks_and_the_env_batch(tasks, error):
    env = make_task_env("point_nav", torch.zeros(3, 2))
    with pytest.raises(error, match=r"^tasks: got .*; expected a \[3, 2\] tensor"):
        env.transform[-1].set_tasks(tasks)


@no_cuda
@pytest.mark.parametrize("device", ["cuda", "cuda:0", torch.device("cuda")])
def test_make_env_refuses_cuda_without_a_cuda_device(device):
    with pytest.raises(InvalidValue, match=r"^device: got .*cuda.* \(no CUDA device is available on this machine\); "
                                           r"expected one of 'cpu', 'auto'"):
        make_env("point_nav", 2, device=device)


@no_cuda
def test_make_proposal_refuses_cuda_without_a_cuda_device():
    with pytest.raises(InvalidValue, match=r"^device: got 'cuda' \(no CUDA device is available on this machine\)"):
        make_proposal("random", "point_nav", num_tasks=2, trajectories_per_task=1, num_skills=2,
                      discriminator_hidden=[8], device="cuda")


def test_make_env_device_names():
    assert make_env("point_nav", 2, device="auto").device.type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(InvalidValue, match=r"^device: got 'gpu'; expected a torch.device or one of 'cpu', 'cuda', "
                                           r"'auto'"):
        make_env("point_nav", 2, device="gpu")


# DIAYN's loss and the discriminator reward: batches without the keys they read

K, B = 4, 8


def _transitions(skill_width=K):
    skill = torch.eye(skill_width)[torch.randint(skill_width, (B,))]
    return TensorDict({
        "observation": torch.randn(B, 2), "skill": skill, "action": torch.rand(B, 2) * 2 - 1,
        "next": {"observation": torch.randn(B, 2), "skill": skill, "reward": torch.zeros(B, 1),
                 "done": torch.zeros(B, 1, dtype=torch.bool), "terminated": torch.zeros(B, 1, dtype=torch.bool)},
    }, [B])


def _diayn_loss():
    return DIAYNLoss(make_skill_actor(2, K, 2, hidden=(8,)), make_skill_qvalue(2, K, 2, hidden=(8,)),
                     make_discriminator(2, K, hidden=(8,)), num_skills=K)


@pytest.mark.parametrize("missing", ["skill", ("next", "observation")])
def test_diayn_loss_names_a_missing_key(missing):
    batch = _transitions()
    del batch[missing]
    with pytest.raises(InvalidValue, match=rf"^tensordict: got a TensorDict of batch size \[8\] \(no "
                                           rf"{re.escape(repr(missing))}\); expected a batch of transitions with "):
        _diayn_loss()(batch)


def test_diayn_loss_names_a_skill_of_another_width():
    with pytest.raises(InvalidValue, match=r"^tensordict\['skill'\]: got a tensor of shape \[8, 5\] .*; expected "
                                           r"one-hot skills \[\*B, 4\] \(num_skills\)"):
        _diayn_loss()(_transitions(skill_width=5))


@pytest.mark.parametrize("observation_key, missing", [("observation", "skill"),
                                                      (("next", "observation"), ("next", "observation"))])
def test_discriminator_reward_names_a_missing_key(observation_key, missing):
    reward = DiscriminatorReward(make_discriminator(2, K, hidden=(8,)), K, observation_key=observation_key)
    batch = _transitions()
    del batch[missing]
    with pytest.raises(InvalidValue, match=rf"^tensordict: got a TensorDict of batch size \[8\] \(no "
                                           rf"{re.escape(repr(missing))}\); expected a batch of transitions with"):
        reward(batch)


def test_discriminator_reward_in_an_env_without_skills_asks_for_a_skill_transform():
    env = make_env("point_nav", 2, horizon=3).append_transform(
        DiscriminatorReward(make_discriminator(2, K, hidden=(8,)), K))
    with pytest.raises(InvalidValue, match=r"^env: got a TransformedEnv \(no 'skill'\); expected an env writing "
                                           r"\['observation', 'skill'\] before this DiscriminatorReward \(append a "
                                           r"SkillTransform first\)"):
        env.rollout(2)


def test_house_format_describes_tensordicts_and_modules_briefly():
    assert str(InvalidValue("x", TensorDict({}, [2, 3]), "y")) == "x: got a TensorDict of batch size [2, 3]; expected y"
    assert str(InvalidType("x", torch.nn.Linear(2, 2), "y")) == "x: got a Linear; expected y"


@pytest.mark.parametrize("loader", ["load_maml_policy", "load_diayn_checkpoint", "load_vime_checkpoint"])
def test_a_checkpoint_path_that_is_not_a_path_is_named(loader):
    from umrl import checkpoints

    with pytest.raises(InvalidType, match=r"^path: got 123; expected a checkpoint file or run directory"):
        getattr(checkpoints, loader)(123)


@pytest.mark.parametrize("recipe, key", [("maml", "num_threads"), ("diayn", "num_threads"), ("vime", "num_threads")])
def test_thread_counts_beyond_any_machine_are_refused_before_openmp_aborts(recipe, key):
    from umrl.configs import ConfigError, validate
    from umrl.configs.diayn import DIAYNConfig
    from umrl.configs.maml import MAMLConfig
    from umrl.configs.vime import VIMEConfig

    schema = {"maml": MAMLConfig, "diayn": DIAYNConfig, "vime": VIMEConfig}[recipe]
    with pytest.raises(ConfigError, match=rf"{key}: got 100000; expected an integer in \[1, 1024\]"):
        validate(compose(recipe, [f"{key}=100000"]), schema)
