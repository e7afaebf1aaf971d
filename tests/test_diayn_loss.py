"""DIAYNLoss: SACLoss + discriminator cross-entropy, fresh pseudo-rewards, separated gradients, renamable keys."""
import math

import pytest
import torch
from tensordict import TensorDict

from umrl.modules.discriminator import make_discriminator
from umrl.modules.sac import make_skill_actor, make_skill_qvalue
from umrl.objectives.diayn import DIAYNLoss

OBS, ACT, K, B = 3, 2, 4, 16
pytestmark = pytest.mark.filterwarnings("ignore:No target network updater")


def make_loss(skill_key="skill", **kwargs):
    torch.manual_seed(0)
    actor = make_skill_actor(OBS, K, ACT, hidden=(16,), skill_key=skill_key)
    qvalue = make_skill_qvalue(OBS, K, ACT, hidden=(16,), skill_key=skill_key)
    kwargs.setdefault("num_skills", K)
    return DIAYNLoss(actor, qvalue, make_discriminator(OBS, K, hidden=(16,)), **kwargs)


def make_data(skill="skill", reward="reward", observation="observation"):
    g = torch.Generator().manual_seed(1)
    z = torch.eye(K)[torch.randint(K, (B,), generator=g)]
    return TensorDict(
        {
            "observation": torch.randn(B, OBS, generator=g),
            skill: z,
            "action": torch.rand(B, ACT, generator=g) * 2 - 1,
            "next": {
                observation: torch.randn(B, OBS, generator=g),
                "observation": torch.randn(B, OBS, generator=g),
                skill: z,
                reward: torch.full((B, 1), 1000.0),  # stale: must be ignored
                "done": torch.zeros(B, 1, dtype=torch.bool),
                "terminated": torch.zeros(B, 1, dtype=torch.bool),
            },
        },
        [B],
    )


def param_groups(loss):
    groups = {
        "actor": list(loss.sac_loss.actor_network_params.values(True, True)),
        "qvalue": list(loss.sac_loss.qvalue_network_params.values(True, True)),
        "discriminator": list(loss.discriminator.parameters()),
    }
    if isinstance(loss.sac_loss.log_alpha, torch.nn.Parameter):
        groups["alpha"] = [loss.sac_loss.log_alpha]
    return groups


@pytest.mark.parametrize("fixed_alpha", [True, False])
def test_each_loss_reaches_only_its_parameters(fixed_alpha):
    owner = {"loss_actor": "actor", "loss_qvalue": "qvalue", "loss_discriminator": "discriminator",
             "loss_alpha": None if fixed_alpha else "alpha"}
    for name, expected in owner.items():
        loss = make_loss(fixed_alpha=fixed_alpha, target_entropy=-float(ACT))
        out = loss(make_data())
        if expected is None:
            assert not out[name].requires_grad and out[name] == 0
            continue
        out[name].backward()
        for group, params in param_groups(loss).items():
            touched = any(p.grad is not None and p.grad.abs().sum() > 0 for p in params)
            assert touched == (group == expected), f"{name} reached {group}: {touched}"


def test_outputs_and_fresh_pseudo_reward():
    loss = make_loss()
    data = make_data()
    out = loss(data)
    for key in ("alpha", "entropy", "discriminator_accuracy", "pseudo_reward"):
        assert not out[key].requires_grad
    logits = loss.discriminator.module(data["observation"])
    label = data["skill"].argmax(-1)
    expected_reward = torch.log_softmax(logits, -1).gather(-1, label[:, None]) + math.log(K)
    torch.testing.assert_close(out["pseudo_reward"], expected_reward.mean().detach())
    torch.testing.assert_close(out["loss_discriminator"], torch.nn.functional.cross_entropy(logits, label))
    torch.testing.assert_close(out["discriminator_accuracy"], (logits.argmax(-1) == label).float().mean())
    assert out["alpha"] == pytest.approx(0.1)
    # the stored reward (1000) plays no part: Q targets use the relabelled reward
    data["next", "reward"].zero_()
    torch.manual_seed(3)
    a = loss(data)["loss_qvalue"]
    data["next", "reward"].fill_(-5.0)
    torch.manual_seed(3)
    assert loss(data)["loss_qvalue"] == a


def test_one_discriminator_forward_serves_reward_and_loss():
    loss = make_loss()
    calls = []
    loss.discriminator.module.register_forward_hook(lambda *_: calls.append(1))
    out = loss(make_data())
    assert len(calls) == 1
    # the reward is scored on detached logits: D's gradient is the cross-entropy's alone
    out["loss_discriminator"].backward()
    got = [p.grad.clone() for p in loss.discriminator.parameters()]
    loss.zero_grad()
    data = make_data()
    logits = loss.discriminator.module(data["observation"])
    torch.nn.functional.cross_entropy(logits, data["skill"].argmax(-1)).backward()
    for g, p in zip(got, loss.discriminator.parameters()):
        torch.testing.assert_close(g, p.grad)


def test_input_not_mutated():
    loss = make_loss()
    data = make_data()
    before = data.clone()
    loss(data)
    assert set(data.keys(True, True)) == set(before.keys(True, True))
    assert (data == before).all()


def test_set_keys_renames():
    loss = make_loss()
    torch.manual_seed(4)
    reference = loss(make_data())
    renamed = make_loss(skill_key="z")
    renamed.set_keys(skill="z", reward="r_diayn", discriminator_observation="observation")
    data = make_data(skill="z", reward="r_diayn")
    torch.manual_seed(4)
    out = renamed(data)
    for key in ("loss_actor", "loss_qvalue", "loss_discriminator", "pseudo_reward"):
        torch.testing.assert_close(out[key], reference[key])
    assert (data["next", "r_diayn"] == 1000).all()
    # the discriminator now scores another state
    renamed.set_keys(discriminator_observation=("next", "observation"))
    torch.manual_seed(4)
    assert renamed(data)["loss_discriminator"] != reference["loss_discriminator"]
    with pytest.raises(ValueError, match="not an accepted"):
        renamed.set_keys(skil="z")


def test_bad_inputs():
    with pytest.raises(ValueError, match="num_skills"):
        make_loss(num_skills=1)
    with pytest.raises(ValueError, match="alpha_init"):
        make_loss(alpha_init=0.0)
