"""collect: [T, N, H] batches, masks, and post-update collection that really runs each task's adapted params."""
import pytest
import torch
from tensordict import TensorDict

from umrl.envs import get_task_family, make_task_env
from umrl.modules.policy import make_gaussian_policy
from umrl.rollout import collect

T, N, H = 3, 2, 7


def _setup():
    torch.manual_seed(0)
    tasks = get_task_family("point_nav").sample(T, torch.Generator().manual_seed(0))
    env = make_task_env("point_nav", tasks.repeat_interleave(N, 0), horizon=H)
    return env, make_gaussian_policy(2, 2, hidden=(8,)), tasks


def _last_layer(params):
    """Keys of the output layer's weight and bias (the MLP's last Linear)."""
    keys = [k for k in params.keys(True, True) if k[-1] in ("weight", "bias") and params.get(k).shape[-1] == 8]
    weight = next(k for k in keys if k[-1] == "weight")
    return weight, weight[:-1] + ("bias",)


def test_pre_update_collection_shapes_mask_and_tasks():
    env, policy, tasks = _setup()
    td = collect(env, policy, num_tasks=T, horizon=H)
    assert td.batch_size == (T, N, H)
    for key in ("observation", "action", "action_log_prob", "loc", "scale", "step_count", ("next", "reward"),
                ("next", "done"), "mask"):
        assert key in td.keys(True), key
    assert td["mask"].shape == (T, N, H) and td["mask"][..., 0].all()
    assert td["step_count"][0, 0, :, 0].tolist() == list(range(H))
    torch.testing.assert_close(td["task"][:, :, 0], tasks.unsqueeze(1).expand(T, N, 2))
    with pytest.raises(ValueError, match="num_tasks"):
        collect(env, policy, num_tasks=4, horizon=H)


def test_post_update_collection_uses_each_tasks_adapted_params():
    env, policy, _ = _setup()
    theta = TensorDict.from_module(policy).detach()
    adapted = theta.expand(T).clone()
    weight, bias = _last_layer(adapted)
    adapted.get(weight).zero_()
    target = torch.tensor([[0.3, -0.2], [-0.5, 0.1], [0.05, 0.4]])
    adapted.set(bias, target.clone())
    td = collect(env, policy, num_tasks=T, horizon=H, params=adapted)
    # the mean action of every step of task t is exactly that task's adapted output bias (θ would give other values)
    torch.testing.assert_close(td["loc"], target[:, None, None, :].expand(T, N, H, 2))
    log_prob = torch.distributions.Independent(torch.distributions.Normal(td["loc"], td["scale"]), 1).log_prob(
        td["action"]
    )
    torch.testing.assert_close(td["action_log_prob"], log_prob)
    with pytest.raises(ValueError, match="per-task params"):
        collect(env, policy, num_tasks=T, horizon=H, params=adapted[:2])
    shared = collect(env, policy, num_tasks=T, horizon=H, params=theta)
    assert not torch.allclose(shared["loc"][:, :, 0], target[:, None, :].expand(T, N, 2))
