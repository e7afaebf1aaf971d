"""Task-batched policy evaluation: agrees with a per-task functional_call loop; the hand-derived derivatives of the
ReLU MLP and the MAML HVP built on them agree with autograd; device plumbing of the MAML step."""
import pytest
import torch
from tensordict import TensorDict
from torch import nn
from torch.func import functional_call

from umrl.envs import get_task_family, make_task_env
from umrl.modules.batched_mlp import BatchedGaussianMLP, ReLUMLPLinearization, declare_batched_layers
from umrl.modules.policy import make_gaussian_policy
from umrl.objectives.maml import MAMLLoss
from umrl.objectives.policy_gradient import compute_advantages
from umrl.optim.meta_hvp import AnalyticHVP, ExactHVP, GaussNewtonHVP, make_meta_hvp
from umrl.optim.trpo import TRPOStep
from umrl.rollout import FunctionalPolicy, collect

T, N, H, OBS, ACT = 3, 2, 5, 2, 2


def _policy(in_keys=("observation",), obs=OBS):
    torch.manual_seed(0)
    return make_gaussian_policy(obs, ACT, hidden=(6, 5), init_std=0.7, in_keys=in_keys).double()


def _batch(policy, seed=0):
    """A [T, N, H] batch with actions, log-probs and loc/scale from per-task perturbed parameters."""
    g = torch.Generator().manual_seed(seed)
    td = TensorDict({
        "observation": torch.randn(T, N, H, OBS, generator=g, dtype=torch.float64),
        "advantage": torch.randn(T, N, H, 1, generator=g, dtype=torch.float64),
        "mask": torch.rand(T, N, H, generator=g) > 0.2,
        "next": {"reward": torch.randn(T, N, H, 1, generator=g, dtype=torch.float64)},
    }, batch_size=[T, N, H])
    params = TensorDict.from_module(policy).detach().expand(T).clone()
    for value in params.values(True, True):
        value.add_(0.1 * torch.randn(value.shape, generator=g, dtype=value.dtype))
    with torch.no_grad():
        td.update(_reference_dist_params(policy, params, td).select("loc", "scale"))
    td["action"] = td["loc"] + td["scale"] * torch.randn(td["loc"].shape, generator=g, dtype=torch.float64)
    td["action_log_prob"] = policy.build_dist_from_params(td).log_prob(td["action"])
    return td


def _reference_dist_params(policy, params, td):
    """The per-task reference: a plain loop over tasks with torch.func.functional_call."""
    net = FunctionalPolicy(policy, task_loop=True).net
    outs = [functional_call(net, dict(params[t].flatten_keys(".").items()), (td[t].select(*net.in_keys),))
            for t in range(params.shape[0])]
    return torch.stack(outs)


def test_recognises_the_gaussian_policy_and_not_other_networks():
    assert FunctionalPolicy(_policy()).batched is not None
    assert FunctionalPolicy(_policy(("observation", "skill"), obs=4)).batched is not None
    assert FunctionalPolicy(_policy(), task_loop=False).batched is None
    policy = _policy()
    policy.module[0].module[0][1] = nn.Dropout(0.0)  # not element-wise: falls back to vmap
    assert BatchedGaussianMLP.from_net(FunctionalPolicy(policy).net) is None
    with pytest.raises(ValueError, match="task_loop"):
        FunctionalPolicy(policy, task_loop="yes")


@pytest.mark.parametrize("in_keys", [("observation",), ("observation", "skill")])
def test_batched_dist_params_match_the_per_task_loop(in_keys):
    policy = _policy(in_keys, obs=OBS + (2 if len(in_keys) > 1 else 0))
    td = _batch(_policy()).select("observation")
    td["skill"] = torch.randn(T, N, H, 2, dtype=torch.float64)
    params = TensorDict.from_module(policy).detach().expand(T).clone().apply(lambda x: x + torch.rand_like(x))
    batched = FunctionalPolicy(policy).dist_params(params, td)
    reference = _reference_dist_params(policy, params, td)
    for key in ("loc", "scale"):
        assert batched[key].shape == (T, N, H, ACT)
        torch.testing.assert_close(batched[key], reference[key], rtol=1e-12, atol=1e-12)


def test_features_are_what_the_last_linear_layer_reads():
    policy = _policy()
    td = _batch(policy)
    params = TensorDict.from_module(policy).detach().expand(T).clone().apply(lambda x: x + torch.rand_like(x))
    batched = BatchedGaussianMLP.from_net(FunctionalPolicy(policy).net)
    features = batched.features(params, [td["observation"]])
    assert features.shape == (T, N, H, 5)  # the last hidden width
    kind, weight_key, bias_key = batched.layers[-1]
    assert kind == "linear"
    loc = torch.einsum("tnhi,toi->tnho", features, params.get(weight_key)) + params.get(bias_key)[:, None, None]
    torch.testing.assert_close(loc, _reference_dist_params(policy, params, td)["loc"], rtol=1e-12, atol=1e-12)


def test_batched_maml_step_matches_the_per_task_loop():
    """Adapted params, surrogate, KL, meta-gradient and Gauss-Newton HVP: batched == loop to float tolerance."""
    policy = _policy()
    support, query = _batch(policy, seed=1), _batch(policy, seed=2)
    losses = {name: MAMLLoss(policy, inner_lr=0.5, task_loop=loop) for name, loop in (("batched", None),
                                                                                      ("loop", True))}
    assert losses["batched"].functional_policy.batched is not None
    leaves = list(losses["batched"].params.values(True, True))
    v = torch.randn(sum(p.numel() for p in leaves), generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    results = {}
    for name, loss in losses.items():
        adapted = loss.adapt(support)
        out = loss(loss.pack(support, query, adapted))
        surrogate, kl = out["loss_objective"], out["trust_region_kl"]
        grad = torch.autograd.grad(surrogate, leaves)
        results[name] = (adapted.detach(), surrogate.detach(), kl.detach(), torch.cat([g.reshape(-1) for g in grad]),
                         GaussNewtonHVP(loss).product(support, query)(v))
    (a_b, s_b, k_b, g_b, h_b), (a_l, s_l, k_l, g_l, h_l) = results["batched"], results["loop"]
    for key in a_b.keys(True, True):
        torch.testing.assert_close(a_b.get(key), a_l.get(key), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(s_b, s_l, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(k_b, k_l, rtol=1e-10, atol=1e-12)
    assert k_b > 0 and g_b.abs().sum() > 0 and h_b.abs().sum() > 0  # the data comes from other params
    torch.testing.assert_close(g_b, g_l, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(h_b, h_l, rtol=1e-10, atol=1e-12)


def test_relu_mlp_linearization_matches_autograd():
    """jvp, vjp and the vjp's directional derivative (a loss's HVP, network curvature included) against autograd."""
    policy = _policy()
    batched = BatchedGaussianMLP.from_net(FunctionalPolicy(policy).net)
    assert batched.is_relu_mlp
    g = torch.Generator().manual_seed(5)
    params = TensorDict.from_module(policy).detach().expand(T).clone()
    for value in params.values(True, True):
        value.add_(0.3 * torch.randn(value.shape, generator=g, dtype=value.dtype)).requires_grad_(True)
    leaves = [t for pair in batched.linear_params(params) for t in pair]
    x = torch.randn(T, N * H, OBS, generator=g, dtype=torch.float64)
    curvature, offset = (torch.rand(T, N * H, ACT, generator=g, dtype=torch.float64) for _ in range(2))
    direction = [(torch.randn_like(w), torch.randn_like(b)) for w, b in batched.linear_params(params)]
    flat_direction = [t for pair in direction for t in pair]

    def loss_of(loc):  # a quadratic loss of the output: gradient curvature * loc + offset, Hessian diag(curvature)
        return (0.5 * curvature * loc * loc + offset * loc).sum()

    loc = batched(params, [x.view(T, N, H, OBS)])[0].reshape(T, N * H, ACT)
    grads = torch.autograd.grad(loss_of(loc), leaves, create_graph=True)
    hvp = torch.autograd.grad(grads, leaves, grad_outputs=flat_direction)
    lin = ReLUMLPLinearization([(w.detach(), b.detach()) for w, b in batched.linear_params(params)], x)
    torch.testing.assert_close(lin.loc, loc.detach(), rtol=1e-12, atol=1e-12)
    r_loc, r_inputs = lin.jvp(direction)
    _, jvp_ref = torch.func.jvp(lambda *p: _apply(p, x), tuple(t.detach() for t in leaves), tuple(flat_direction))
    torch.testing.assert_close(r_loc, jvp_ref, rtol=1e-12, atol=1e-12)
    mine, deltas = lin.vjp(curvature * lin.loc + offset)
    torch.testing.assert_close([t for pair in mine for t in pair], [t.detach() for t in grads], rtol=1e-12,
                               atol=1e-12)
    r_grads = lin.rvjp(direction, r_inputs, deltas, curvature * r_loc)
    torch.testing.assert_close([t for pair in r_grads for t in pair], list(hvp), rtol=1e-12, atol=1e-12)
    assert all(t.abs().sum() > 0 for t in hvp)


@pytest.mark.parametrize("width_in, width_out", [(7, 2), (2, 7), (5, 5)])
def test_linearization_products_in_either_orientation(width_in, width_out):
    """_affine and _sample_sum give the plain products whether they compute a narrow output transposed or not."""
    g = torch.Generator().manual_seed(2)
    t, m = 3, 11
    xs = [torch.randn(t, m, width_in, generator=g, dtype=torch.float64) for _ in range(2)]
    ws = [torch.randn(t, width_out, width_in, generator=g, dtype=torch.float64) for _ in range(2)]
    bias = torch.randn(t, width_out, generator=g, dtype=torch.float64)
    plain = sum(torch.einsum("tmi,toi->tmo", x, w) for x, w in zip(xs, ws))
    for b, expected in ((None, plain), (bias, plain + bias[:, None])):
        out = ReLUMLPLinearization._affine(list(zip(xs, ws)), b)
        assert out.shape == (t, m, width_out)
        torch.testing.assert_close(out, expected, rtol=1e-12, atol=1e-12)
    deltas = [torch.randn(t, m, width_out, generator=g, dtype=torch.float64) for _ in range(2)]
    out = ReLUMLPLinearization._sample_sum(list(zip(deltas, xs)))
    assert out.shape == (t, width_out, width_in)
    expected = sum(torch.einsum("tmo,tmi->toi", d, x) for d, x in zip(deltas, xs))
    torch.testing.assert_close(out, expected, rtol=1e-12, atol=1e-12)


def _apply(flat_params, x):
    """The ReLU MLP's output for its linear layers' (weight, bias) given as one flat tuple."""
    h = x
    pairs = list(zip(flat_params[::2], flat_params[1::2]))
    for i, (w, b) in enumerate(pairs):
        h = torch.baddbmm(b.unsqueeze(-2), h, w.mT)
        h = h.relu() if i < len(pairs) - 1 else h
    return h


@pytest.mark.parametrize("first_order", [False, True])
@pytest.mark.parametrize("in_keys", [("observation",), ("observation", "skill")])
def test_analytic_gauss_newton_hvp_equals_autograds(first_order, in_keys):
    """The hand-derived J^T F J product equals the autograd one and the exact KL Hessian through the inner step."""
    policy = _policy(in_keys, obs=OBS + (2 if len(in_keys) > 1 else 0))
    loss = MAMLLoss(policy, inner_lr=0.5, first_order=first_order)
    assert AnalyticHVP.supports(loss)
    support, query = _batch(_policy(), seed=1), _batch(_policy(), seed=2)
    for td in (support, query):
        td["skill"] = torch.randn(T, N, H, 2, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    with torch.no_grad():  # the query's recorded loc/scale from the adapted policy: the KL's minimum at θ
        query.update(loss.functional_policy.dist_params(loss.adapt(support), query).select("loc", "scale"))
    leaves = list(loss.params.values(True, True))
    grad = torch.autograd.grad(ExactHVP(loss).kl(support, query), leaves, create_graph=True)
    grad = torch.cat([x.reshape(-1) for x in grad])
    analytic, autograd = AnalyticHVP(loss).product(support, query), GaussNewtonHVP(loss).product(support, query)
    for seed in range(2):
        v = torch.randn(grad.numel(), generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
        exact = torch.cat([h.reshape(-1) for h in torch.autograd.grad(grad @ v, leaves, retain_graph=True)])
        torch.testing.assert_close(analytic(v), autograd(v), rtol=1e-10, atol=1e-12)
        torch.testing.assert_close(analytic(v), exact, rtol=1e-6, atol=1e-9)
        assert analytic(v).abs().sum() > 0


def test_analytic_gauss_newton_hvp_with_a_clamped_scale_and_a_subsample():
    policy = _policy()
    with torch.no_grad():
        policy.module[0].module[1].state_independent_scale[0] = -20.0  # exp(-20) < scale_lb: clamped, no gradient
    loss = MAMLLoss(policy, inner_lr=0.5)
    support, query = _batch(policy, seed=1), _batch(policy, seed=2)
    v = torch.randn(sum(p.numel() for p in loss.params.values(True, True)), dtype=torch.float64,
                    generator=torch.Generator().manual_seed(0))
    products = [hvp(loss, fraction=0.5, generator=torch.Generator().manual_seed(9)).product(support, query)(v)
                for hvp in (AnalyticHVP, GaussNewtonHVP)]
    torch.testing.assert_close(*products, rtol=1e-10, atol=1e-12)


def test_analytic_gauss_newton_hvp_refuses_what_it_cannot_differentiate():
    policy = _policy()
    support, query = _batch(policy, seed=1), _batch(policy, seed=2)
    with pytest.raises(ValueError, match="needs a ReLU MLP Gaussian policy"):
        AnalyticHVP(MAMLLoss(policy, inner_lr=0.5, task_loop=True)).product(support, query)
    with pytest.raises(ValueError, match="num_inner_steps=1"):
        AnalyticHVP(MAMLLoss(policy, inner_lr=0.5, num_inner_steps=2)).product(support, query)
    tanh = make_gaussian_policy(OBS, ACT, hidden=(4,)).double()
    tanh.module[0].module[0][1] = nn.Tanh()
    assert not AnalyticHVP.supports(MAMLLoss(tanh))


def _objective_and_kl(loss, support, query, adapted=None):
    out = loss(loss.pack(support, query, adapted))
    return out["loss_objective"], out["trust_region_kl"]


def _tiny_maml_step(device: str, hvp: str = "gauss_newton"):
    """Collect, adapt, collect post-update, one TRPO meta-step (subsampled Gauss-Newton HVP ``hvp``, a
    :data:`~umrl.optim.meta_hvp.META_HVPS` name): all on ``device``."""
    torch.manual_seed(0)
    tasks = get_task_family("point_nav").sample(T, torch.Generator().manual_seed(0))
    env = make_task_env("point_nav", tasks.repeat_interleave(N, 0).to(device), horizon=H, device=device)
    policy = make_gaussian_policy(2, 2, hidden=(8,)).to(device)
    loss = MAMLLoss(policy, inner_lr=0.5)
    support = compute_advantages(collect(env, policy, num_tasks=T, horizon=H))
    adapted = loss.adapt(support)
    query = compute_advantages(collect(env, policy, num_tasks=T, horizon=H, params=adapted.detach()))
    out = loss(loss.pack(support, query))
    before = [p.detach().clone() for p in policy.parameters()]
    generator = torch.Generator(device=device).manual_seed(0)
    strategy = make_meta_hvp(hvp, loss, fraction=0.5, generator=generator)
    # On this 3-task, 5-step batch the quadratic KL model is loose: the first acceptable step lies 15-16 backtracks
    # down, on one side or the other of the default limit depending on the CPU's kernels.
    info = TRPOStep(loss.params, hvp=strategy, max_kl=0.05, max_backtracks=40)(
        lambda: _objective_and_kl(loss, support, query), initial=_objective_and_kl(loss, support, query, adapted),
        batch=loss.pack(support, query))
    tensors = [*support.values(True, True), *query.values(True, True), *adapted.values(True, True),
               *out.values(True, True), *policy.parameters()]
    assert {t.device.type for t in tensors} == {torch.device(device).type}
    assert info["accepted"] == 1.0
    assert any(not torch.equal(p, b) for p, b in zip(policy.parameters(), before))


@pytest.mark.parametrize("hvp", ["gauss_newton", "analytic"])
def test_tiny_maml_step_with_explicit_cpu_device(hvp):
    _tiny_maml_step("cpu", hvp)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("hvp", ["gauss_newton", "analytic"])
def test_tiny_maml_step_on_cuda(hvp):
    _tiny_maml_step("cuda", hvp)


def test_the_policy_declares_its_layers_and_an_unsupported_layer_fails_its_declaration():
    policy = _policy(("observation", "skill"), obs=4)
    batched = FunctionalPolicy(policy).batched
    declared = {key for pair in batched.linear_keys() for key in pair} | {batched.scale_key}
    assert declared == set(TensorDict.from_module(FunctionalPolicy(policy).net).keys(True, True))
    module = policy.module[0]
    mlp, head = module.module.net  # behind the input concatenation: keys found by identity, not by path
    mlp[1] = nn.Dropout(0.0)
    with pytest.raises(ValueError, match="layer 1 of the policy's MLP is a Dropout"):
        declare_batched_layers(module, mlp, head)
