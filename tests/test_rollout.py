"""collect: [T, N, H] batches, masks, post-update collection that really runs each task's adapted params, and the
fixed-horizon loop that CUDA graphs replay."""
import pytest
import torch
from tensordict import TensorDict

import umrl.rollout as rollout_module
from umrl.envs import get_task_family, make_task_env
from umrl.modules.policy import make_gaussian_policy
from umrl.rollout import FunctionalPolicy, collect, fixed_horizon_steps
from umrl.trajectories import trajectory_mask

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
    with pytest.raises(ValueError, match=r"params: got a TensorDict of batch size \[2\]; expected .*batch size \[3\]"):
        collect(env, policy, num_tasks=T, horizon=H, params=adapted[:2])
    shared = collect(env, policy, num_tasks=T, horizon=H, params=theta)
    assert not torch.allclose(shared["loc"][:, :, 0], target[:, None, :].expand(T, N, 2))


def _steered(env):
    """A policy callable steering each point to its goal (so copies finish early) with a little noise."""
    def act(td):
        to_goal = (env.transform[-1].tasks - td["position"]) / 0.1
        return td.set("action", to_goal.clamp(-1, 1) + 1e-3 * torch.randn_like(to_goal))
    return act


def test_fixed_horizon_steps_match_env_rollout_up_to_each_first_done():
    goals = torch.tensor([[0.3, 0.2], [-0.25, 0.05], [0.4, -0.4], [0.0, 0.1]])
    env = make_task_env("point_nav", goals, horizon=20)
    act = _steered(env)
    torch.manual_seed(1)
    reference = env.rollout(20, act, auto_reset=True, break_when_any_done=False)
    torch.manual_seed(1)
    fixed = fixed_horizon_steps(env, act, env.reset(), 20)
    mask = trajectory_mask(reference["next", "done"])
    assert (mask.sum(-1) < 20).all()  # every copy ended early, so auto-resets happened in the reference
    assert torch.equal(mask, trajectory_mask(fixed["next", "done"]))
    assert set(fixed.keys(True, True)) == set(reference.keys(True, True))
    for key in reference.keys(True, True):
        assert torch.equal(fixed[key][mask], reference[key][mask]), key
    assert not torch.equal(fixed["observation"], reference["observation"])  # after done: stepped on, not reset


def _check_rollout_consistent(td, policy, params, tasks):
    """Every step of a [T, N, H] point_nav batch follows the env's dynamics, the task reward and ``params``."""
    T = td.shape[0]
    torch.testing.assert_close(td["observation"][:, :, 0], torch.zeros_like(td["observation"][:, :, 0]))
    moved = td["position"] + 0.1 * td["action"].clamp(-1, 1)
    torch.testing.assert_close(td["next", "position"], moved)
    goal = tasks.view(T, -1, 1, 2)
    torch.testing.assert_close(td["next", "reward"], -(td["next", "position"] - goal).norm(dim=-1, keepdim=True))
    per_task = params if params.batch_dims else params.expand(T)
    expected = FunctionalPolicy(policy).dist_params(per_task, td.reshape(T, -1))
    torch.testing.assert_close(td["loc"].reshape(T, -1, 2), expected["loc"])
    steps = torch.arange(td.shape[-1], device=td.device).expand(td.shape)
    assert torch.equal(td["step_count"][..., 0][td["mask"]], steps[td["mask"]])


def test_rollout_consistency_check_holds_for_env_rollout():
    """The check the CUDA-graph test relies on passes for plain collection and fails on wrong parameters."""
    env, policy, tasks = _setup()
    td = collect(env, policy, num_tasks=T, horizon=H)
    theta = TensorDict.from_module(policy).detach()
    _check_rollout_consistent(td, policy, theta, tasks.repeat_interleave(N, 0))
    with pytest.raises(AssertionError):
        _check_rollout_consistent(td, policy, theta.apply(lambda p: p + 0.1), tasks.repeat_interleave(N, 0))


def test_cudagraphs_refused_off_cuda_and_for_host_physics():
    env, policy, _ = _setup()
    with pytest.raises(ValueError, match="CUDA device.*cudagraphs=False"):
        collect(env, policy, num_tasks=T, horizon=H, cudagraphs=True)
    cheetah = make_task_env("half_cheetah", torch.ones(2, 1), horizon=3)
    with pytest.raises(ValueError, match="pure device work.*cudagraphs=False"):
        collect(cheetah, make_gaussian_policy(17, 6, hidden=(8,)), num_tasks=2, horizon=3, cudagraphs=True)


@pytest.mark.skipif(torch.cuda.is_available(), reason="on a GPU the test below records and replays for real")
def test_graph_path_plumbing_on_the_cpu(monkeypatch):
    """Off CUDA ``CudaGraphModule`` runs its function eagerly: the cudagraphs path's inputs, fixed-horizon loop and
    cache give consistent batches for shared and per-task parameters (what the CUDA test checks after replays)."""
    monkeypatch.setattr(rollout_module, "check_cudagraphs", lambda env: None)
    env, policy, tasks = _setup()
    theta = TensorDict.from_module(policy).detach()
    adapted = theta.expand(T).clone().apply(lambda p: p + 0.1 * torch.randn_like(p))
    for _ in range(3):
        shared = collect(env, policy, num_tasks=T, horizon=H, cudagraphs=True)
        per_task = collect(env, policy, num_tasks=T, horizon=H, params=adapted, cudagraphs=True)
        _check_rollout_consistent(shared, policy, theta, tasks.repeat_interleave(N, 0))
        _check_rollout_consistent(per_task, policy, adapted, tasks.repeat_interleave(N, 0))
        assert shared.batch_size == per_task.batch_size == (T, N, H) and shared["mask"].all()
    assert len(rollout_module._GRAPHS[env]) == 2


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_replayed_rollout_follows_live_params_env_state_and_tasks():
    """Recorded once, replayed after in-place updates of the policy and new tasks: every replay reads the live ones."""
    torch.manual_seed(0)
    family = get_task_family("point_nav")
    env = make_task_env("point_nav", family.sample(T).repeat_interleave(N, 0), horizon=H, device="cuda")
    policy = make_gaussian_policy(2, 2, hidden=(8,)).to("cuda")
    graphs = []
    for call in range(5):
        tasks = family.sample(T).repeat_interleave(N, 0).cuda()
        env.transform[-1].set_tasks(tasks)
        with torch.no_grad():
            for p in policy.parameters():
                p.add_(0.05 * torch.randn_like(p))
        theta = TensorDict.from_module(policy).detach()
        adapted = theta.expand(T).clone().apply(lambda p: p + 0.1 * torch.randn_like(p))
        shared = collect(env, policy, num_tasks=T, horizon=H, cudagraphs=True)
        per_task = collect(env, policy, num_tasks=T, horizon=H, params=adapted, cudagraphs=True)
        _check_rollout_consistent(shared, policy, theta, tasks)
        _check_rollout_consistent(per_task, policy, adapted, tasks)
        graphs.append({key: graph for key, (_, graph) in rollout_module._GRAPHS[env].items()})
    # CudaGraphModule warms up on the first call and captures on the second (its counter then stays at 2): the same two
    # modules served every call and hold a captured graph, so calls 3-5 replayed it rather than re-recording.
    assert len(graphs[-1]) == 2 and all(g == graphs[0] for g in graphs)
    assert all(isinstance(graph.graph, torch.cuda.CUDAGraph) for graph in graphs[-1].values())
