"""SkillTransform: one uniform skill per episode, resampled on (partial) resets, pinnable, spec-checked."""
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from umrl.envs import make_env
from umrl.transforms.skill import SkillTransform


def skill_env(num_envs, num_skills=5, horizon=100):
    return make_env("point_nav", num_envs, seed=0, horizon=horizon).append_transform(SkillTransform(num_skills))


@pytest.mark.parametrize("num_envs", [1, 4])
def test_check_env_specs(num_envs):
    env = skill_env(num_envs)
    check_env_specs(env)
    spec = env.full_state_spec["skill"]
    assert spec.shape == (num_envs, 5) and spec.dtype == torch.float32


def test_skill_constant_within_episode_and_resampled_across():
    torch.manual_seed(0)
    env = skill_env(16, num_skills=10, horizon=5)
    td = env.rollout(15, break_when_any_done=False)  # three episodes of 5 steps per copy
    skills = td["skill"].argmax(-1)  # [16, 15]
    assert (td["skill"].sum(-1) == 1).all()
    episodes = skills.reshape(16, 3, 5)
    assert (episodes == episodes[..., :1]).all(), "the skill changed inside an episode"
    assert torch.equal(td["next", "skill"][:, :4], td["skill"][:, :4]), "the skill is not carried into 'next'"
    assert (episodes[:, 1, 0] != episodes[:, 0, 0]).any() and (episodes[:, 2, 0] != episodes[:, 1, 0]).any()


def test_partial_reset_resamples_only_reset_copies():
    torch.manual_seed(1)
    env = skill_env(64, num_skills=10)
    td = env.reset()
    before = td["skill"].clone()
    reset = torch.zeros(64, 1, dtype=torch.bool)
    reset[:32] = True
    td["_reset"] = reset
    after = env.reset(td)["skill"]
    assert torch.equal(after[32:], before[32:])
    changed = (after[:32].argmax(-1) != before[:32].argmax(-1)).float().mean()
    assert changed > 0.6  # 0.9 expected with 10 skills


def test_uniform_over_resets_chi_square():
    torch.manual_seed(2)
    num_skills, num_envs, resets = 5, 500, 20
    env = skill_env(num_envs, num_skills=num_skills)
    counts = sum(env.reset()["skill"].sum(0) for _ in range(resets))
    expected = num_envs * resets / num_skills
    chi2 = ((counts - expected) ** 2 / expected).sum()
    assert chi2 < 18.47, f"chi-square {chi2:.1f} over 4 dof (p < 0.001): counts {counts.tolist()}"


def test_pin_fixes_skills_until_unpinned():
    torch.manual_seed(3)
    env = skill_env(4, num_skills=5)
    transform = env.transform[-1]
    transform.pin(torch.tensor([0, 1, 2, 4]))
    td = env.rollout(3)
    assert (td["skill"].argmax(-1) == torch.tensor([0, 1, 2, 4])[:, None]).all()
    transform.pin(torch.tensor(3))  # broadcast to every copy
    assert (env.reset()["skill"].argmax(-1) == 3).all()
    transform.pin(None)
    draws = torch.stack([env.reset()["skill"].argmax(-1) for _ in range(10)])
    assert len(draws.unique()) > 1


def test_forward_outside_env():
    transform = SkillTransform(7)
    td = transform(TensorDict({}, batch_size=[6]))
    assert td["skill"].shape == (6, 7) and (td["skill"].sum(-1) == 1).all()
    transform.pin(torch.arange(6))
    assert (transform(TensorDict({}, batch_size=[6]))["skill"].argmax(-1) == torch.arange(6)).all()


@pytest.mark.parametrize("bad", [1, 0, 2.5])
def test_bad_num_skills(bad):
    with pytest.raises(ValueError, match="num_skills"):
        SkillTransform(bad)


def test_bad_pin():
    transform = SkillTransform(3)
    with pytest.raises(ValueError, match="0, 3"):
        transform.pin(torch.tensor([0, 3]))
    with pytest.raises(ValueError, match="integer"):
        transform.pin(torch.tensor([0.5]))
    env = skill_env(4, num_skills=3)
    env.transform[-1].pin(torch.tensor([0, 1]))
    with pytest.raises(ValueError, match="do not fit"):
        env.reset()
