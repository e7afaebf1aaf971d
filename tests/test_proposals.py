"""Task proposals: env batch layout, per-task rewards of the right shape and value, errors that say what to fix."""
import math

import pytest
import torch
from tensordict import TensorDict

from umrl.modules.discriminator import make_discriminator
from umrl.modules.policy import make_gaussian_policy
from umrl.proposals import make_proposal
from umrl.rollout import collect

T, N, H = 3, 2, 5


def _rollout(proposal, seed=0):
    torch.manual_seed(seed)
    return collect(proposal.env, make_gaussian_policy(2, 2, hidden=(8,)), num_tasks=proposal.num_tasks, horizon=H)


def _discriminator_reward(discriminator, td, num_skills):
    logits = discriminator(TensorDict({"observation": td["next", "observation"]}, td.shape))["skill_logits"]
    z = td["skill"].argmax(-1, keepdim=True)
    return torch.log_softmax(logits, -1).gather(-1, z) + math.log(num_skills)


def test_oracle_rewards_are_negative_distances_to_each_tasks_goal():
    proposal = make_proposal("oracle", "point_nav", num_tasks=T, trajectories_per_task=N, horizon=H)
    assert proposal.env.batch_size == (T * N,)
    goals = proposal.resample(torch.Generator().manual_seed(3))
    assert goals.shape == (T, 2)
    td = _rollout(proposal)
    assert td["next", "reward"].shape == (T, N, H, 1)
    expected = -(td["next", "observation"] - goals[:, None, None]).norm(dim=-1, keepdim=True)
    torch.testing.assert_close(td["next", "reward"], expected)
    assert not torch.equal(proposal.resample(torch.Generator().manual_seed(4)), goals)


def test_random_proposal_uses_a_seeded_frozen_discriminator_one_skill_per_task():
    proposal = make_proposal("random", "point_nav", num_tasks=T, trajectories_per_task=N, horizon=H, num_skills=6,
                             seed=7, discriminator_hidden=(16,))
    skills = proposal.resample(torch.Generator().manual_seed(0))
    assert skills.shape == (T,) and len(set(skills.tolist())) == T
    td = _rollout(proposal)
    assert (td["skill"].argmax(-1) == skills[:, None, None]).all()
    reference = make_discriminator(2, 6, hidden=(16,), seed=7)  # same seed, same weights
    torch.testing.assert_close(td["next", "reward"], _discriminator_reward(reference, td, 6))
    discriminator = proposal.env.transform[-1].discriminator
    assert not any(p.requires_grad for p in discriminator.parameters())
    full = make_proposal("random", "point_nav", trajectories_per_task=1, num_skills=6, discriminator_hidden=(16,))
    assert full.num_tasks == 6 and full.resample().tolist() == list(range(6))


@pytest.mark.parametrize("tiny_diayn_checkpoint", [None, [1]], indirect=True, ids=["whole_observation", "dims"])
def test_diayn_proposal_reads_the_discriminator_from_a_checkpoint(tiny_diayn_checkpoint):
    checkpoint, discriminator = tiny_diayn_checkpoint
    proposal = make_proposal("diayn", "point_nav", trajectories_per_task=N, horizon=H, diayn_checkpoint=checkpoint)
    assert proposal.num_tasks == 4 and proposal.num_skills == 4
    proposal.resample()
    td = _rollout(proposal)
    assert td["next", "reward"].shape == (4, N, H, 1)
    torch.testing.assert_close(td["next", "reward"], _discriminator_reward(discriminator, td, 4))
    with pytest.raises(ValueError, match="exceeds"):
        make_proposal("diayn", "point_nav", num_tasks=5, diayn_checkpoint=checkpoint)
    with pytest.raises(ValueError, match=r"observation size: got 2 \(the discriminator of .*\); expected 17, the "
                                         r"observation size of env 'half_cheetah'"):
        make_proposal("diayn", "half_cheetah", diayn_checkpoint=checkpoint)


def test_proposal_errors_say_what_to_fix(tmp_path):
    with pytest.raises(ValueError, match="valid choices"):
        make_proposal("skills", "point_nav")
    with pytest.raises(ValueError, match="diayn_checkpoint"):
        make_proposal("diayn", "point_nav")
    with pytest.raises(FileNotFoundError):
        make_proposal("diayn", "point_nav", diayn_checkpoint=tmp_path / "missing")
