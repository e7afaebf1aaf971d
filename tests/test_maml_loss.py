"""MAMLLoss: second-order meta-gradient vs finite differences, first order, reach, zero inner steps, adapt, another
inner loss."""
import re

import pytest
import torch
from tensordict import TensorDict

from umrl.modules.policy import make_gaussian_policy
from umrl.objectives.maml import MAMLLoss, gaussian_kl
from umrl.objectives.policy_gradient import vpg_loss
from umrl.optim.meta_hvp import AnalyticHVP, ExactHVP, GaussNewtonHVP
from umrl.optim.trpo import TRPOStep
from umrl.rollout import FunctionalPolicy

T, N, H, OBS, ACT = 2, 3, 4, 2, 2


def _policy(seed=0, dtype=torch.float64):
    torch.manual_seed(seed)
    return make_gaussian_policy(OBS, ACT, hidden=(5,), init_std=0.7).to(dtype)


def _batch(policy, params=None, seed=0, dtype=torch.float64):
    """A [T, N, H] batch whose actions, log-probs and loc/scale come from `params` (per task) or the policy."""
    g = torch.Generator().manual_seed(seed)
    td = TensorDict(
        {
            "observation": torch.randn(T, N, H, OBS, generator=g, dtype=dtype),
            "advantage": torch.randn(T, N, H, 1, generator=g, dtype=dtype),
            "mask": torch.ones(T, N, H, dtype=torch.bool),
            "next": {"reward": torch.randn(T, N, H, 1, generator=g, dtype=dtype)},
        },
        batch_size=[T, N, H],
    )
    td["mask"][0, 0, -1] = False
    functional = FunctionalPolicy(policy)
    p = TensorDict.from_module(policy).detach() if params is None else params.detach()
    with torch.no_grad():
        dist_params = functional.dist_params(p, td)
        td.update(dist_params.select("loc", "scale"))
        td["action"] = td["loc"] + td["scale"] * torch.randn(td["loc"].shape, generator=g, dtype=dtype)
        td["action_log_prob"] = functional.log_prob(p, td)
    return td


def _grad(loss_module, support, query):
    params = loss_module.params
    leaves = list(params.values(True, True))
    loss = loss_module(loss_module.pack(support, query))["loss_objective"]
    return torch.cat([g.reshape(-1) for g in torch.autograd.grad(loss, leaves)])


def test_second_order_meta_gradient_matches_central_finite_differences():
    policy = _policy()
    loss_module = MAMLLoss(policy, inner_lr=0.5)
    support = _batch(policy, seed=1)
    with torch.no_grad():
        adapted = loss_module.adapt(support)
    query = _batch(policy, adapted, seed=2)
    analytic = _grad(loss_module, support, query)
    leaves = list(loss_module.params.values(True, True))
    numeric, eps = [], 1e-6
    for p in leaves:
        flat = p.data.view(-1)
        for i in range(flat.numel()):
            old = flat[i].item()
            values = []
            for sign in (1, -1):
                flat[i] = old + sign * eps
                with torch.no_grad():
                    values.append(loss_module(loss_module.pack(support, query))["loss_objective"].item())
            flat[i] = old
            numeric.append((values[0] - values[1]) / (2 * eps))
    numeric = torch.tensor(numeric, dtype=torch.float64)
    torch.testing.assert_close(analytic, numeric, rtol=1e-5, atol=1e-7)

    first = _grad(MAMLLoss(policy, inner_lr=0.5, first_order=True), support, query)
    assert (first - numeric).norm() > 1e-3 * numeric.norm()  # the Hessian terms matter at this inner lr
    # first order = gradient of the outer loss w.r.t. the adapted params, summed over tasks
    phi = adapted.clone().requires_grad_(True)
    outer, _, _ = loss_module._surrogate_and_kl(phi, query)
    d_phi = torch.autograd.grad(outer, [phi.get(k) for k in phi.keys(True, True)])
    torch.testing.assert_close(first, torch.cat([g.sum(0).reshape(-1) for g in d_phi]))


@pytest.mark.parametrize("task_loop", [False, True, None])
def test_meta_gradient_reaches_every_parameter(task_loop):
    policy = _policy(dtype=torch.float32)
    loss_module = MAMLLoss(policy, task_loop=task_loop)
    support = _batch(policy, seed=3, dtype=torch.float32)
    with torch.no_grad():
        query = _batch(policy, loss_module.adapt(support), seed=4, dtype=torch.float32)
    out = loss_module(loss_module.pack(support, query))
    assert set(out.keys()) >= {"loss_objective", "kl", "inner_loss", "return_pre", "return_post"}
    assert not out["kl"].requires_grad and out["kl"].abs() < 1e-5
    out["loss_objective"].backward()
    for name, p in policy.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_zero_inner_steps_is_plain_policy_gradient():
    policy = _policy()
    loss_module = MAMLLoss(policy, num_inner_steps=0)
    query = _batch(policy, seed=5)
    maml_grad = _grad(loss_module, query, query)
    leaves = list(loss_module.params.values(True, True))
    pg = vpg_loss(FunctionalPolicy(policy).log_prob(loss_module.params, query), query).mean()
    torch.testing.assert_close(maml_grad, torch.cat([g.reshape(-1) for g in torch.autograd.grad(pg, leaves)]))


def test_adapt_is_one_sgd_step_per_task_and_detached_under_no_grad():
    policy = _policy()
    loss_module = MAMLLoss(policy, inner_lr=0.3)
    support = _batch(policy, seed=6)
    with torch.no_grad():
        adapted = loss_module.adapt(support)
    assert adapted.batch_size == (T,) and not any(v.requires_grad for v in adapted.values(True, True))
    params = loss_module.params
    for t in range(T):
        loss = vpg_loss(FunctionalPolicy(policy).log_prob(params, support[t]), support[t])
        grads = torch.autograd.grad(loss, list(params.values(True, True)))
        for (key, p), g in zip(params.items(True, True), grads):
            torch.testing.assert_close(adapted[t].get(key), p.detach() - 0.3 * g)
    with pytest.raises(ValueError, match=r"\[T, N, H\]"):
        loss_module.adapt(support[0])


def test_gaussian_kl_matches_torch():
    g = torch.Generator().manual_seed(0)
    l0, l1 = torch.randn(2, 5, 3, generator=g)
    s0, s1 = torch.rand(2, 5, 3, generator=g) + 0.1
    ref = torch.distributions.kl_divergence(
        torch.distributions.Independent(torch.distributions.Normal(l0, s0), 1),
        torch.distributions.Independent(torch.distributions.Normal(l1, s1), 1),
    )
    torch.testing.assert_close(gaussian_kl(l0, s0, l1, s1), ref)


@pytest.mark.parametrize("first_order", [False, True])
def test_gauss_newton_hvp_equals_the_exact_kl_hessian_through_the_inner_step(first_order):
    policy = _policy()
    loss_module = MAMLLoss(policy, inner_lr=0.5, first_order=first_order)
    support = _batch(policy, seed=7)
    with torch.no_grad():
        query = _batch(policy, loss_module.adapt(support), seed=8)
    leaves = list(loss_module.params.values(True, True))
    kl = ExactHVP(loss_module).kl(support, query)
    grad = torch.cat([g.reshape(-1) for g in torch.autograd.grad(kl, leaves, create_graph=True)])
    hvp = GaussNewtonHVP(loss_module).product(support, query)
    for seed in range(2):
        v = torch.randn(grad.numel(), generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
        exact = torch.cat([h.reshape(-1) for h in torch.autograd.grad(grad @ v, leaves, retain_graph=True)])
        torch.testing.assert_close(hvp(v), exact, rtol=1e-6, atol=1e-9)
    # the closure's KL (against the recorded collecting policy) has the same Hessian at θ
    closure_kl = loss_module(loss_module.pack(support, query))["trust_region_kl"]
    g2 = torch.cat([g.reshape(-1) for g in torch.autograd.grad(closure_kl, leaves, create_graph=True)])
    exact = torch.cat([h.reshape(-1) for h in torch.autograd.grad(g2 @ v, leaves)])
    torch.testing.assert_close(hvp(v), exact, rtol=1e-5, atol=1e-8)


def test_reusing_the_inner_step_graph_gives_the_same_meta_gradient():
    policy = _policy()
    loss_module = MAMLLoss(policy, inner_lr=0.5)
    support = _batch(policy, seed=1)
    adapted = loss_module.adapt(support)  # with its graph, as the recipe keeps it for the meta-step
    query = _batch(policy, adapted, seed=2)
    leaves = list(loss_module.params.values(True, True))
    loss = loss_module(loss_module.pack(support, query, adapted))["loss_objective"]
    reused = torch.cat([g.reshape(-1) for g in torch.autograd.grad(loss, leaves)])
    torch.testing.assert_close(reused, _grad(loss_module, support, query), rtol=0, atol=0)
    assert reused.abs().sum() > 0


@pytest.mark.parametrize(
    "kwargs, message",
    [({"inner_lr": float("nan")}, "inner_lr: got nan; expected a finite number > 0"),
     ({"inner_lr": 0.0}, "inner_lr: got 0.0; expected a finite number > 0"),
     ({"num_inner_steps": 1.5}, "num_inner_steps: got 1.5; expected an integer >= 0")],
)
def test_bad_hyperparameters_name_the_argument(kwargs, message):
    policy = make_gaussian_policy(2, 2, hidden=[4])
    with pytest.raises((TypeError, ValueError), match=re.escape(message)):
        MAMLLoss(policy, **kwargs)


def per_trajectory_pg_loss(log_prob, support, *, advantage_key="advantage", mask_key="mask"):
    """A second inner loss: VPG summed over each trajectory's valid steps, then averaged over trajectories [T]."""
    weights = support[mask_key].to(log_prob.dtype)
    return -(log_prob * support[advantage_key].squeeze(-1) * weights).sum(-1).mean(-1)


def test_another_inner_loss_adapts_through_itself_and_trains_a_trpo_step():
    policy = _policy()
    loss_module = MAMLLoss(policy, inner_lr=0.2, inner_loss_fn=per_trajectory_pg_loss)
    support = _batch(policy, seed=1)
    adapted = loss_module.adapt(support)
    theta = loss_module.params
    for t in range(T):  # one SGD step on the given loss, not on VPG's
        loss = per_trajectory_pg_loss(FunctionalPolicy(policy).log_prob(theta, support[t]), support[t])
        for (key, p), g in zip(theta.items(True, True), torch.autograd.grad(loss, list(theta.values(True, True)))):
            torch.testing.assert_close(adapted[t].get(key), p.detach() - 0.2 * g)
    vpg_adapted = MAMLLoss(policy, inner_lr=0.2).adapt(support).detach()
    assert not all(torch.allclose(a, b) for a, b in zip(adapted.detach().values(True, True),
                                                          vpg_adapted.values(True, True)))
    query = _batch(policy, adapted, seed=2)
    leaves = list(theta.values(True, True))
    v = torch.randn(sum(p.numel() for p in leaves), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    exact = ExactHVP(loss_module).product(support, query)(v)  # the Gauss-Newton product holds for any inner loss
    torch.testing.assert_close(GaussNewtonHVP(loss_module).product(support, query)(v), exact, rtol=1e-6, atol=1e-9)
    assert exact.abs().sum() > 0
    with pytest.raises(ValueError, match="the VPG inner loss"):
        AnalyticHVP(loss_module).product(support, query)

    before = [p.detach().clone() for p in leaves]
    batch = loss_module.pack(support, query)

    def closure():
        out = loss_module(batch)
        return out["loss_objective"], out["trust_region_kl"]

    info = TRPOStep(theta, hvp=GaussNewtonHVP(loss_module), max_kl=0.01)(closure, batch=batch)
    assert info["accepted"] == 1.0 and info["improvement"] > 0
    assert any(not torch.equal(p, b) for p, b in zip(leaves, before))


def test_inner_loss_fn_must_be_callable():
    with pytest.raises(TypeError, match="inner_loss_fn: got 'vpg'; expected a callable"):
        MAMLLoss(_policy(), inner_loss_fn="vpg")
