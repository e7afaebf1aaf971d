"""policy_gradient: masks, returns, baseline fit, advantages and the VPG surrogate against hand computations."""
import pytest
import torch
from tensordict import TensorDict

from umrl.objectives import policy_gradient
from umrl.objectives.policy_gradient import (
    baseline_features,
    compute_advantages,
    episode_lengths,
    episode_returns,
    fit_linear_baseline,
    trajectory_mask,
    vpg_loss,
)
from umrl.process import torch_threads


def _batch(T=3, N=4, H=6, obs_dim=2, seed=0, end_early=True):
    g = torch.Generator().manual_seed(seed)
    done = torch.zeros(T, N, H, 1, dtype=torch.bool)
    done[..., -1, :] = True
    if end_early:
        done[0, 0, 2] = True  # goal reached at t=2: the steps after it belong to a reset episode
    step = torch.arange(H).expand(T, N, H).unsqueeze(-1).clone()
    step[0, 0, 3:] = torch.arange(H - 3).unsqueeze(-1)
    return TensorDict(
        {
            "observation": torch.randn(T, N, H, obs_dim, generator=g),
            "step_count": step,
            "next": {"reward": torch.randn(T, N, H, 1, generator=g), "done": done},
        },
        batch_size=[T, N, H],
    )


def _returns_loop(reward, mask, gamma):
    out = torch.zeros_like(reward)
    running = torch.zeros_like(reward[..., 0])
    for t in reversed(range(reward.shape[-1])):
        running = reward[..., t] * mask[..., t] + gamma * running * mask[..., t]
        out[..., t] = running
    return out


def test_trajectory_mask_stops_after_first_done():
    done = torch.tensor([[0, 0, 1, 0, 1]], dtype=torch.bool).unsqueeze(-1)
    assert trajectory_mask(done).tolist() == [[True, True, True, False, False]]
    with pytest.raises(ValueError, match="trailing singleton"):
        trajectory_mask(done.squeeze(-1))


def test_advantages_with_lambda_one_are_returns_minus_baseline():
    td = compute_advantages(_batch(), gamma=0.9, lmbda=1.0, normalize=False)
    mask = td["mask"]
    assert mask[0, 0].tolist() == [True, True, True, False, False, False] and mask[1].all()
    expected = _returns_loop(td["next", "reward"].squeeze(-1), mask.float(), 0.9)
    torch.testing.assert_close(td["value_target"].squeeze(-1), expected)
    torch.testing.assert_close(td["advantage"], (td["value_target"] - td["state_value"]) * mask.unsqueeze(-1))
    assert (td["state_value"][0, 0, 3:] == 0).all()


def test_gae_runs_the_masked_steps_after_an_episode_as_one_segment(monkeypatch):
    """Rows of one-step episodes (a goal at the start), their auto-reset episodes done at every step too: the GAE gets
    two segments per row (the episode, then the masked rest), not one per masked step, which TorchRL pads to the
    longest segment; the advantages are the loop's."""
    td = _batch(T=2, N=3, H=50)
    td["next", "done"][0] = True
    segments = []
    original = policy_gradient.vec_generalized_advantage_estimate

    def counting(*args, **kwargs):
        ends = args[5]
        segments.append(int((ends | (torch.arange(ends.shape[-2]) == ends.shape[-2] - 1).unsqueeze(-1)).sum()))
        return original(*args, **kwargs)

    monkeypatch.setattr(policy_gradient, "vec_generalized_advantage_estimate", counting)
    td = compute_advantages(td, gamma=0.9, lmbda=1.0, normalize=False)
    assert segments == [2 * 3 + 3] * 2  # task 0: 2 per row (50 per row before); task 1: its whole rows
    mask = td["mask"]
    expected = _returns_loop(td["next", "reward"].squeeze(-1), mask.float(), 0.9)
    torch.testing.assert_close(td["value_target"].squeeze(-1), expected)


def test_baseline_is_exact_when_targets_are_linear_in_features_and_per_task():
    td = _batch(end_early=False)
    feats = baseline_features(td)
    assert feats.shape == (3, 4, 6, 2 * 2 + 4)
    w = torch.randn(3, feats.shape[-1], 1, dtype=torch.float64)
    targets = (feats.double() @ w.unsqueeze(-3)).float()
    fitted = fit_linear_baseline(feats, targets, torch.ones(3, 4, 6, dtype=torch.bool), reg_coeff=1e-10)
    torch.testing.assert_close(fitted, targets, rtol=1e-3, atol=1e-3)


def test_baseline_fit_at_ant_width_is_exact_on_two_threads():
    """214 features (ant's): torch's multi-threaded LU returned wrong solutions or failed at this width on an AMD
    EPYC; the fit solves on one thread, so a 2-thread run gets the 1-thread fit exactly."""
    gen = torch.Generator().manual_seed(0)
    feats = torch.randn(5, 20, 20, 214, generator=gen, dtype=torch.float64)
    targets = feats @ torch.randn(5, 1, 214, 1, generator=gen, dtype=torch.float64)
    mask = torch.ones(5, 20, 20, dtype=torch.bool)
    with torch_threads(1):
        one_thread = fit_linear_baseline(feats, targets, mask, reg_coeff=1e-10)
    with torch_threads(2):
        two_threads = fit_linear_baseline(feats, targets, mask, reg_coeff=1e-10)
        assert torch.get_num_threads() == 2
    torch.testing.assert_close(one_thread, targets)
    assert torch.equal(two_threads, one_thread)


def test_baseline_fit_raises_instead_of_returning_garbage():
    td = _batch()
    feats = baseline_features(td)
    feats[0, 0, 0, 0] = float("nan")
    with pytest.raises(FloatingPointError, match="not finite"):
        fit_linear_baseline(feats, torch.zeros(3, 4, 6, 1), torch.ones(3, 4, 6, dtype=torch.bool))


def test_normalised_advantages_have_zero_mean_unit_std_per_task():
    td = compute_advantages(_batch(), normalize=True)
    for i in range(3):
        a = td["advantage"][i][td["mask"][i]]
        assert abs(a.mean().item()) < 1e-5 and abs(a.std(unbiased=False).item() - 1) < 1e-4


def test_vpg_loss_and_returns_are_masked_means_and_sums():
    td = compute_advantages(_batch(), normalize=False)
    log_prob = torch.randn(3, 4, 6)
    loss = vpg_loss(log_prob, td)
    assert loss.shape == (3,)
    m = td["mask"][1]
    expected = -(log_prob[1][m] * td["advantage"][1].squeeze(-1)[m]).mean()
    torch.testing.assert_close(loss[1], expected)
    ret = episode_returns(td)
    assert ret.shape == (3, 4)
    torch.testing.assert_close(ret[0, 0], td["next", "reward"][0, 0, :3].sum())
    lengths = episode_lengths(td)  # the first episode of copy (0, 0) ends at t=2, every other one at the horizon
    expected_lengths = torch.full((3, 4), 6)
    expected_lengths[0, 0] = 3
    assert torch.equal(lengths, expected_lengths)
    with pytest.raises(ValueError, match="expected the batch"):
        vpg_loss(log_prob[..., :-1], td)
