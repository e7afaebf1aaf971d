"""VIMELoss (dynamics ELBO) and the VIMEBonus transform."""
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from umrl.envs import make_env
from umrl.modules.bnn import BayesianDynamics
from umrl.objectives.vime import VIMELoss
from umrl.transforms.vime_bonus import VIMEBonus


def _linear_data(n, generator):
    a_mat = torch.tensor([[0.9, 0.2], [-0.1, 1.0]])
    obs = torch.randn(n, 2, generator=generator)
    act = torch.rand(n, 2, generator=generator) * 2 - 1
    nxt = obs @ a_mat.T + 0.3 * act
    return TensorDict({"observation": obs, "action": act, ("next", "observation"): nxt}, [n])


def test_elbo_improves_on_a_linear_system():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    train, held_out = _linear_data(512, g), _linear_data(256, g)
    bnn = BayesianDynamics(2, 2)
    bnn.update_normalizer(train["observation"], train["action"], train["next", "observation"])
    loss_fn = VIMELoss(bnn, dataset_size=512)
    optim = torch.optim.Adam(bnn.parameters(), lr=1e-2)
    with torch.no_grad():
        before, held_before = loss_fn(train)["loss_dynamics"].item(), loss_fn.log_likelihood(held_out).item()
    for _ in range(300):
        optim.zero_grad()
        loss_fn(train[torch.randint(512, (64,))])["loss_dynamics"].backward()
        optim.step()
    with torch.no_grad():
        after, held_after = loss_fn(train)["loss_dynamics"].item(), loss_fn.log_likelihood(held_out).item()
    assert after < before - 1.0
    assert held_after > held_before + 1.0


def test_loss_value_keys_and_gradients():
    g = torch.Generator().manual_seed(1)
    td = _linear_data(32, g).rename_key_("observation", "state")
    snapshot = td.clone()
    bnn = BayesianDynamics(2, 2)
    loss_fn = VIMELoss(bnn, dataset_size=100, num_samples=3)
    loss_fn.set_keys(observation="state")
    torch.manual_seed(5)
    out = loss_fn(td)
    torch.manual_seed(5)
    expected = bnn.kl_to_prior() / 100 - loss_fn.log_likelihood(td)
    torch.testing.assert_close(out["loss_dynamics"], expected)
    assert set(out.keys()) == {"loss_dynamics", "kl_prior", "log_likelihood", "elbo"}
    assert not out["kl_prior"].requires_grad and not out["elbo"].requires_grad
    out["loss_dynamics"].backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in bnn.parameters())
    assert (td == snapshot).all()
    with pytest.raises(ValueError, match="dataset_size"):
        VIMELoss(bnn, dataset_size=0)


def test_transform_in_env_writes_bonus_and_keeps_env_reward():
    torch.manual_seed(0)
    bonus = VIMEBonus(BayesianDynamics(2, 2), eta=1e-2)
    env = make_env("point_nav", num_envs=3, seed=0).append_transform(bonus)
    check_env_specs(env)
    td = env.rollout(4)
    nxt = td["next"]
    assert nxt["intrinsic_reward"].shape == (3, 4, 1)
    torch.testing.assert_close(nxt["reward"], nxt["extrinsic_reward"] + nxt["intrinsic_reward"])
    assert (nxt["extrinsic_reward"] == 0).all() and (nxt["intrinsic_reward"] > 0).all()
    # the per-step medians entered the history: check_env_specs' steps plus the 4 rollout steps
    assert (~bonus.median_history.isnan()).sum() >= 4


def test_forward_relabels_a_batch_once_with_median_normalisation():
    torch.manual_seed(0)
    env = make_env("point_nav", num_envs=8, seed=0)
    td = env.rollout(10, break_when_any_done=False)  # [8, 10]
    td["next", "reward"] = torch.ones_like(td["next", "reward"])
    bonus = VIMEBonus(BayesianDynamics(2, 2), eta=0.5)
    bonus.dynamics.update_normalizer(td["observation"], td["action"], td["next", "observation"])
    bonus(td)
    first = td["next", "intrinsic_reward"].clone()
    # history holds only this batch's median, so the median bonus is eta
    assert first.median().item() == pytest.approx(0.5, rel=1e-5)
    torch.testing.assert_close(td["next", "reward"], 1 + first)
    bonus.update_history = False
    history = bonus.median_history.clone()
    bonus(td)
    torch.testing.assert_close(td["next", "extrinsic_reward"], torch.ones_like(first))
    torch.testing.assert_close(td["next", "reward"], 1 + td["next", "intrinsic_reward"])
    assert torch.equal(bonus.median_history.nan_to_num(-1), history.nan_to_num(-1))
    with pytest.raises(ValueError, match="eta"):
        VIMEBonus(bonus.dynamics, eta=-1.0)


def test_info_gain_is_larger_for_unfamiliar_transitions():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    obs = torch.rand(2048, 2, generator=g) - 0.5  # familiar region: the unit square around 0
    act = torch.rand(2048, 2, generator=g) * 2 - 1
    nxt = obs + 0.1 * act
    bnn = BayesianDynamics(2, 2)
    bnn.update_normalizer(obs, act, nxt)
    loss_fn = VIMELoss(bnn, dataset_size=2048)
    optim = torch.optim.Adam(bnn.parameters(), lr=1e-2)
    data = TensorDict({"observation": obs, "action": act, ("next", "observation"): nxt}, [2048])
    for _ in range(200):
        optim.zero_grad()
        loss_fn(data[torch.randint(2048, (128,))])["loss_dynamics"].backward()
        optim.step()
    far = obs + 3.0
    noise = bnn.sample_noise(10)
    familiar = bnn.info_gain(obs[:256], act[:256], nxt[:256], noise=noise).median()
    novel = bnn.info_gain(far[:256], act[:256], far[:256] + 0.1 * act[:256], noise=noise).median()
    assert novel > 3 * familiar
