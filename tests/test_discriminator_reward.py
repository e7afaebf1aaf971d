"""DiscriminatorReward: r = log D(z|s') + log K, no grad, relabelling with the current discriminator; the env's own
reward kept under ("next", "env_reward"); declared keys."""
import math

import pytest
import torch
from torchrl.envs.utils import check_env_specs

from umrl.envs import make_env, make_task_env
from umrl.envs.mujoco_gym import EnvRewardToKey
from umrl.modules.discriminator import discriminator_logits, make_discriminator
from umrl.transforms.discriminator_reward import DiscriminatorReward
from umrl.transforms.skill import SkillTransform

K = 6


def by_hand(discriminator, observation, skill):
    logits = discriminator.module(observation)
    return torch.log_softmax(logits, -1).gather(-1, skill.argmax(-1, keepdim=True)) + math.log(K)


def reward_env(discriminator, num_envs=4, **kwargs):
    env = make_env("point_nav", num_envs, seed=0).append_transform(SkillTransform(K))
    return env.append_transform(DiscriminatorReward(discriminator, K, **kwargs))


def test_check_env_specs_single_and_batched():
    disc = make_discriminator(2, K, hidden=(16,), seed=0)
    check_env_specs(reward_env(disc, num_envs=1))
    check_env_specs(reward_env(disc, num_envs=5))


def test_reward_matches_hand_computation_on_s_t():
    torch.manual_seed(0)
    disc = make_discriminator(2, K, hidden=(16, 16))
    td = reward_env(disc).rollout(5)
    expected = by_hand(disc, td["observation"], td["skill"])
    torch.testing.assert_close(td["next", "reward"], expected)
    assert not td["next", "reward"].requires_grad
    # s_{t+1} would give a different reward: the first observation is the origin for every copy
    assert not torch.allclose(expected, by_hand(disc, td["next", "observation"], td["skill"]))


def test_observation_key_next_state():
    torch.manual_seed(0)
    disc = make_discriminator(2, K, hidden=(16,))
    td = reward_env(disc, observation_key=("next", "observation")).rollout(4)
    torch.testing.assert_close(td["next", "reward"], by_hand(disc, td["next", "observation"], td["skill"]))


def test_forward_relabels_with_current_discriminator():
    torch.manual_seed(0)
    disc = make_discriminator(2, K, hidden=(16,))
    transform = DiscriminatorReward(disc, K)
    td = reward_env(disc).rollout(5).reshape(-1)
    td["next", "env_reward"] = torch.randn(td.shape[0], 1)
    env_reward = td["next", "env_reward"].clone()
    stale = td["next", "reward"].clone()
    with torch.no_grad():  # the discriminator is trained elsewhere: the transform must see the new weights
        for p in disc.parameters():
            p.add_(torch.randn_like(p))
    out = transform(td)
    assert out is td
    fresh = by_hand(disc, td["observation"], td["skill"])
    torch.testing.assert_close(td["next", "reward"], fresh)
    assert not torch.allclose(fresh, stale)
    torch.testing.assert_close(td["next", "env_reward"], env_reward)


GOALS = torch.tensor([[1.0, 0.5], [-2.0, 1.0], [0.0, -1.5], [3.0, 3.0]])


def goal_reward_env(discriminator, *keep_first):
    """point_nav rewarded by goals (a nonzero env reward), then ``keep_first`` transforms, skills and the skill
    reward."""
    env = make_task_env("point_nav", GOALS, seed=0)
    for transform in (*keep_first, SkillTransform(K), DiscriminatorReward(discriminator, K)):
        env.append_transform(transform)
    return env


def goal_rewards(td):
    """The goal task's reward of each transition, -||s' - g||, recomputed from the rollout."""
    return -torch.linalg.vector_norm(td["next", "observation"] - td["task"], dim=-1, keepdim=True)


def test_env_reward_is_kept_under_its_key_and_the_skill_reward_replaces_it():
    disc = make_discriminator(2, K, hidden=(16,), seed=0)
    env = goal_reward_env(disc)
    check_env_specs(env)
    td = env.rollout(5)
    torch.testing.assert_close(td["next", "env_reward"], goal_rewards(td))
    torch.testing.assert_close(td["next", "reward"], by_hand(disc, td["observation"], td["skill"]))
    assert td["next", "env_reward"].abs().min() > 0 and not torch.allclose(td["next", "reward"], td["next", "env_reward"])
    assert torch.equal(env.reset()["env_reward"], torch.zeros(4, 1))
    assert env.reward_keys == ["reward"]  # one reward for the losses; the env's is an observation entry


def test_an_env_that_already_keeps_its_reward_keeps_it():
    """umrl's MuJoCo envs write their reward to "env_reward" and leave "reward" at zero (EnvRewardToKey): the
    transform must not overwrite the env's reward with that zero."""
    disc = make_discriminator(2, K, hidden=(16,), seed=0)
    td = goal_reward_env(disc, EnvRewardToKey()).rollout(5)
    torch.testing.assert_close(td["next", "env_reward"], goal_rewards(td))
    torch.testing.assert_close(td["next", "reward"], by_hand(disc, td["observation"], td["skill"]))


def test_relabelling_a_batch_without_env_reward_moves_its_reward_there_once():
    disc = make_discriminator(2, K, hidden=(16,), seed=0)
    td = reward_env(disc).rollout(4).reshape(-1).exclude(("next", "env_reward"))
    env_reward = torch.randn(td.shape[0], 1)
    td["next", "reward"] = env_reward.clone()
    transform = DiscriminatorReward(disc, K)
    transform(td)
    torch.testing.assert_close(td["next", "env_reward"], env_reward)
    transform(td)  # a second relabelling leaves the kept reward alone
    torch.testing.assert_close(td["next", "env_reward"], env_reward)
    torch.testing.assert_close(td["next", "reward"], by_hand(disc, td["observation"], td["skill"]))


def test_keys_are_declared():
    disc = make_discriminator(2, K, hidden=(8,))
    transform = DiscriminatorReward(disc, K, observation_key=("next", "observation"))
    assert transform.in_keys == [("next", "observation"), "skill", "reward"]
    assert transform.out_keys == ["reward", "env_reward"]
    assert repr(transform) == ("DiscriminatorReward(num_skills=6, in_keys=[('next', 'observation'), 'skill', "
                               "'reward'], out_keys=['reward', 'env_reward'])")
    custom = DiscriminatorReward(disc, K, reward_key="skill_reward", env_reward_key="task_reward")
    assert custom.out_keys == ["skill_reward", "task_reward"]
    env = make_task_env("point_nav", GOALS, seed=0).append_transform(SkillTransform(K)).append_transform(custom)
    check_env_specs(env)
    td = env.rollout(3)
    torch.testing.assert_close(td["next", "reward"], goal_rewards(td))  # not the transform's key: untouched
    torch.testing.assert_close(td["next", "skill_reward"], by_hand(disc, td["observation"], td["skill"]))


def test_seeded_random_discriminator_is_reproducible_and_keeps_global_rng():
    torch.manual_seed(5)
    state = torch.get_rng_state()
    a = make_discriminator(2, K, seed=3).requires_grad_(False)
    assert torch.equal(torch.get_rng_state(), state)
    b = make_discriminator(2, K, seed=3)
    c = make_discriminator(2, K, seed=4)
    obs = torch.randn(10, 2)
    assert torch.equal(a.module(obs), b.module(obs))
    assert not torch.allclose(a.module(obs), c.module(obs))
    # unseeded calls draw different weights
    assert not torch.allclose(make_discriminator(2, K).module(obs), make_discriminator(2, K).module(obs))
    td = reward_env(a).rollout(3)  # a frozen discriminator works the same way
    torch.testing.assert_close(td["next", "reward"], by_hand(a, td["observation"], td["skill"]))


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda disc: make_discriminator(2, 1), "num_skills"),
        (lambda disc: DiscriminatorReward(disc, 1), "num_skills"),
        (lambda disc: DiscriminatorReward(disc, K + 1).pseudo_reward(torch.zeros(3, 2), torch.zeros(3, K)), "expected"),
    ],
)
def test_bad_inputs(call, match):
    with pytest.raises(ValueError, match=match):
        call(make_discriminator(2, K, hidden=(8,)))


def test_default_init_is_the_reference_xavier_uniform_with_zero_biases():
    """DIAYN's reference MLPs: Glorot-uniform weights U(+-sqrt(6 / (fan_in + fan_out))), zero biases."""
    layers = [m for m in make_discriminator(2, 50, seed=0).modules() if isinstance(m, torch.nn.Linear)]
    assert [tuple(m.weight.shape) for m in layers] == [(300, 2), (300, 300), (50, 300)]
    for layer in layers:
        fan_out, fan_in = layer.weight.shape
        bound = math.sqrt(6.0 / (fan_in + fan_out))
        w = layer.weight.detach()
        assert w.abs().max() <= bound
        assert w.abs().max() > 0.95 * bound  # fills its interval (U(-b, b) has std b / sqrt(3))
        assert w.std().item() == pytest.approx(bound / math.sqrt(3), rel=0.1)
        assert torch.count_nonzero(layer.bias) == 0
    torch_layers = [m for m in make_discriminator(2, 50, seed=0, init="torch").modules()
                    if isinstance(m, torch.nn.Linear)]
    assert all(torch.count_nonzero(m.bias) > 0 for m in torch_layers)  # the other choice really differs
    with pytest.raises(ValueError, match="init must be one of .*'kaiming'"):
        make_discriminator(2, 50, init="kaiming")


def test_input_dims_discriminator_reads_only_those_dims():
    disc = make_discriminator(5, K, hidden=(16,), seed=0, input_dims=[3, 1])
    obs = torch.randn(7, 5)
    changed = obs.clone()
    changed[:, [0, 2, 4]] = torch.randn(7, 3)  # the dims it does not read
    logits = discriminator_logits(disc, obs)
    torch.testing.assert_close(discriminator_logits(disc, changed), logits, rtol=0, atol=0)
    same_net = disc.module[1]  # the MLP behind the selection, fed the chosen dims by hand
    torch.testing.assert_close(same_net(obs[:, [3, 1]]), logits, rtol=0, atol=0)
    assert not torch.equal(discriminator_logits(disc, obs[:, [1, 0, 2, 3, 4]]), logits)  # dim 1 and 3 matter
    assert disc.module[1][0].in_features == 2


@pytest.mark.parametrize("dims", [[], [5], [-1], [1, 1]])
def test_input_dims_are_checked(dims):
    with pytest.raises(ValueError, match=r"input_dims must be distinct observation dims in \[0, 5\)"):
        make_discriminator(5, K, input_dims=dims)
