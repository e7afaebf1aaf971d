"""Meta-test protocol: the first update by hand, the SGD schedule's steps by hand, k=0 from the initial params,
DIAYN-init's skill choice, the learning-rate sweep."""
import copy
import math

import pytest
import torch
from tensordict.nn import NormalParamExtractor, TensorDictModule, TensorDictSequential
from torchrl.modules import ProbabilisticActor, TanhNormal

from umrl.metatest import (
    AdaptationConfig,
    TaskAdapter,
    make_eval_env,
    select_skills,
    sgd_lr_factor,
    sweep_learning_rate,
)
from umrl.modules.policy import make_gaussian_policy
from umrl.objectives.policy_gradient import episode_returns

GOALS = torch.tensor([[0.3, -0.2], [-0.4, 0.1], [0.05, 0.45]])


def _expected_grads(policy, batch, params=None):
    """Per-task gradient of -mean_valid(log N(a; mu(s), sigma) * A), by plain autograd on a module copy.

    ``params`` (per-task, batch ``[T]``): task t's copy holds ``params[t]`` instead of the policy's own weights.
    """
    grads = []
    for t in range(batch.shape[0]):
        module = copy.deepcopy(policy)
        if params is not None:
            with torch.no_grad():
                for name, p in module.named_parameters():
                    p.copy_(params[t].flatten_keys(".")[name])
        data = batch[t]
        out = module(data.select("observation").clone())
        logp = torch.distributions.Normal(out["loc"], out["scale"]).log_prob(data["action"]).sum(-1)
        w = data["mask"].float()
        loss = -(logp * data["advantage"].squeeze(-1) * w).sum() / w.sum()
        module.zero_grad()
        loss.backward()
        grads.append({n: p.grad.clone() for n, p in module.named_parameters()})
    return grads


@pytest.mark.parametrize("optimizer", ["sgd", "adam"])
def test_first_update_matches_hand_computed_step(optimizer):
    torch.manual_seed(0)
    policy = make_gaussian_policy(2, 2, hidden=(8,))
    theta = {n: p.detach().clone() for n, p in policy.named_parameters()}
    config = AdaptationConfig(num_steps=1, num_trajectories=4, horizon=10)
    env = make_eval_env("point_nav", GOALS, 4, seed=0, horizon=10)
    adapter = TaskAdapter(policy, env, len(GOALS), optimizer=optimizer, lr=0.05, config=config)
    batch = adapter.collect()
    assert batch.shape == (3, 4, 10)
    torch.testing.assert_close(batch["task"][:, 0, 0], GOALS)  # task-major layout: copy t*N+n solves task t
    adapter.step(batch)
    for t, grad in enumerate(_expected_grads(policy, batch)):
        for name, g in grad.items():
            # SGD: theta - lr g. Adam's first step (bias-corrected m = g, v = g^2): theta - lr g / (|g| + eps).
            step = g if optimizer == "sgd" else g / (g.abs() + 1e-8)
            got = adapter.params[t].flatten_keys(".")[name]
            torch.testing.assert_close(got, theta[name] - 0.05 * step, rtol=1e-4, atol=1e-6)
    # the policy module itself is untouched: only the per-task copies move
    for name, p in policy.named_parameters():
        torch.testing.assert_close(p.detach(), theta[name])


def test_returns_at_k0_come_from_the_initial_params():
    """A near-deterministic policy moving at constant velocity c: the k=0 return is sum_i -||0.1 i c - g||."""
    horizon = 20
    policy = make_gaussian_policy(2, 2, hidden=(4,), init_std=1e-4)
    params = dict(policy.named_parameters())
    with torch.no_grad():
        for name, p in params.items():
            if "scale" not in name:
                p.zero_()
        params["module.0.module.0.2.bias"].copy_(torch.tensor([0.5, -0.25]))  # the MLP's output bias = mean action
    velocity = 0.1 * torch.tensor([0.5, -0.25])
    positions = velocity * torch.arange(1, horizon + 1).unsqueeze(-1)
    expected = torch.stack([-(positions - g).norm(dim=-1).sum() for g in GOALS])
    config = AdaptationConfig(num_steps=2, num_trajectories=3, horizon=horizon)
    env = make_eval_env("point_nav", GOALS, 3, seed=0, horizon=horizon)
    returns = TaskAdapter(policy, env, len(GOALS), optimizer="adam", lr=0.5, config=config).run()
    assert returns.shape == (3, 3)
    torch.testing.assert_close(returns[0], expected, rtol=1e-3, atol=1e-3)
    assert (returns[1] - expected).abs().max() > 0.1  # after a large update the policy has moved


def _planted_skill_actor(directions: torch.Tensor) -> ProbabilisticActor:
    """Skill k moves (almost deterministically) along directions[k]: loc = 3 * d_k, tiny scale."""
    num_skills = directions.shape[0]
    linear = torch.nn.Linear(num_skills, 4)
    with torch.no_grad():
        linear.weight.zero_()
        linear.weight[:2] = 3.0 * directions.T
        linear.bias.copy_(torch.tensor([0.0, 0.0, -8.0, -8.0]))  # NormalParamExtractor: scale = biased softplus
    module = TensorDictSequential(
        TensorDictModule(linear, in_keys=["skill"], out_keys=["params"]),
        TensorDictModule(NormalParamExtractor(), in_keys=["params"], out_keys=["loc", "scale"]),
    )
    return ProbabilisticActor(module, in_keys=["loc", "scale"], out_keys=["action"], distribution_class=TanhNormal,
                              distribution_kwargs={"low": -1.0, "high": 1.0}, return_log_prob=True,
                              log_prob_key="action_log_prob")


def test_diayn_init_selects_planted_best_skill_and_fine_tunes_it():
    angles = torch.arange(6) * (2 * math.pi / 6)
    directions = torch.stack([angles.cos(), angles.sin()], -1)
    actor = _planted_skill_actor(directions)
    tasks = 0.4 * directions[[3, 1]]  # task 0 lies along skill 3, task 1 along skill 1
    best, returns = select_skills(actor, "point_nav", tasks, 6, num_trajectories=2, seed=0, horizon=10)
    assert best.tolist() == [3, 1]
    assert returns.shape == (2, 6)
    config = AdaptationConfig(num_steps=1, num_trajectories=2, horizon=10)
    env = make_eval_env("point_nav", tasks, 2, seed=0, horizon=10, skills=best, num_skills=6)
    adapter = TaskAdapter(actor, env, 2, optimizer="adam", lr=1e-3, config=config)
    batch = adapter.collect()
    assert (batch["skill"].argmax(-1) == best.view(2, 1, 1)).all()  # fine-tuning runs the chosen skill
    losses = adapter.step(batch)
    assert torch.isfinite(losses).all()
    torch.testing.assert_close(episode_returns(batch).mean(-1), returns[[0, 1], [3, 1]], rtol=1e-3, atol=1e-3)


def test_sweep_picks_the_best_lr_on_the_given_tasks():
    seen = []

    def run(lr, tasks):
        seen.append(tasks)
        return torch.tensor([[0.0, 0.0], [-abs(math.log10(lr) + 2), 0.0]])  # best at lr = 1e-2

    best, scores = sweep_learning_rate(run, [1e-3, 1e-2, 1e-1], torch.zeros(2, 2))
    assert best == pytest.approx(1e-2) and len(scores) == 3 and len(seen) == 3


def test_sgd_lr_factor_schedules_by_hand():
    assert [sgd_lr_factor("constant", k) for k in range(4)] == [1.0, 1.0, 1.0, 1.0]
    assert [sgd_lr_factor("reference", k) for k in range(4)] == [1.0, 0.5, 0.5, 0.5]  # alpha, then alpha / 2
    assert [sgd_lr_factor("reference", k, 0.125) for k in range(3)] == [1.0, 0.5, 0.5]  # always the MAML code's
    assert [sgd_lr_factor("swept", k, 0.125) for k in range(3)] == [1.0, 0.125, 0.125]
    with pytest.raises(ValueError, match=r"sgd_schedule.*\['constant', 'reference', 'swept'\].*'halving'"):
        sgd_lr_factor("halving", 0)
    with pytest.raises(ValueError, match=r"protocol.sgd_schedule.*'halving'"):
        AdaptationConfig(sgd_schedule="halving")
    with pytest.raises(ValueError, match=r"protocol.sgd_later_factor: got 0; expected a finite number > 0"):
        AdaptationConfig(sgd_schedule="swept", sgd_later_factor=0)


@pytest.mark.parametrize("optimizer, schedule, expected", [
    ("sgd", "constant", [0.2, 0.2, 0.2]),
    ("sgd", "reference", [0.2, 0.1, 0.1]),
    ("sgd", "swept", [0.2, 0.05, 0.05]),
    ("adam", "reference", [0.2, 0.2, 0.2]),  # the schedule is SGD's; Adam keeps its lr
])
def test_adapter_steps_follow_the_schedule(optimizer, schedule, expected):
    torch.manual_seed(0)
    policy = make_gaussian_policy(2, 2, hidden=(8,))
    config = AdaptationConfig(num_steps=3, num_trajectories=4, horizon=10, sgd_schedule=schedule,
                              sgd_later_factor=0.25)  # used by "swept" only
    adapter = TaskAdapter(policy, make_eval_env("point_nav", GOALS, 4, seed=0, horizon=10), len(GOALS),
                          optimizer=optimizer, lr=0.2, config=config)
    used = []
    for _ in range(3):
        before = adapter.params.detach().clone()
        batch = adapter.collect()
        used.append(adapter.optimizer.param_groups[0]["lr"])
        adapter.step(batch)
        if optimizer == "sgd":  # the parameters moved by exactly lr_k * g_k, g_k by hand at the current params
            for t, grad in enumerate(_expected_grads(policy, batch, params=before)):
                for name, g in grad.items():
                    got = adapter.params[t].flatten_keys(".")[name]
                    want = before[t].flatten_keys(".")[name] - used[-1] * g
                    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-6)
    assert used == pytest.approx(expected)
