"""TRPOStep / conjugate_gradient: CG solves SPD systems; the line search honours the KL bound or restores exactly."""
import re

import pytest
import torch
from tensordict import TensorDict

from umrl.optim.hvp import KLHessian
from umrl.optim.trpo import TRPOStep, conjugate_gradient


def test_conjugate_gradient_solves_random_spd_system():
    g = torch.Generator().manual_seed(0)
    m = torch.randn(20, 20, generator=g, dtype=torch.float64)
    a = m @ m.T / 20 + torch.eye(20, dtype=torch.float64)
    b = torch.randn(20, generator=g, dtype=torch.float64)
    x = conjugate_gradient(lambda v: a @ v, b, iters=40, residual_tol=1e-24)
    torch.testing.assert_close(x, torch.linalg.solve(a, b), rtol=1e-8, atol=1e-8)
    x5, ax5 = conjugate_gradient(lambda v: a @ v, b, iters=5, with_product=True)
    torch.testing.assert_close(ax5, a @ x5, rtol=1e-10, atol=1e-10)  # the product CG accumulates, no extra matvec


def test_conjugate_gradient_rejects_matrix_rhs():
    with pytest.raises(ValueError, match="1-D"):
        conjugate_gradient(lambda v: v, torch.ones(2, 2))


def _params(seed=0):
    g = torch.Generator().manual_seed(seed)
    return TensorDict(
        {"layer": {"weight": torch.nn.Parameter(torch.randn(3, 4, generator=g))},
         "bias": torch.nn.Parameter(torch.randn(5, generator=g))},
        batch_size=[],
    )


def _flat(params):
    return torch.cat([p.detach().reshape(-1) for p in params.values(True, True)])


def test_line_search_restores_parameters_bit_exactly_when_no_step_improves():
    params = _params()
    theta0 = _flat(params).clone()
    c = torch.linspace(-1, 1, theta0.numel())

    def closure():
        delta = torch.cat([p.reshape(-1) for p in params.values(True, True)]) - theta0
        # the linear term points downhill, the huge quadratic term makes every finite step worse
        return (c * delta).sum() + 1e6 * delta.pow(2).sum(), delta.pow(2).sum()

    info = TRPOStep(params, max_kl=0.01)(closure)
    assert info["accepted"] == 0.0 and info["backtracks"] == 15 and info["rejected_surrogate"] == 15
    assert torch.equal(_flat(params), theta0)
    assert info["direction_s"] > info["cg_s"] > 0 and info["line_search_s"] > 0  # both phases ran and are timed


def test_line_search_accepts_improving_step_within_kl_bound():
    params = _params(1)
    theta0 = _flat(params).clone()
    c = torch.linspace(-1, 1, theta0.numel())
    curvature = torch.linspace(1.0, 3.0, theta0.numel())

    def delta():
        return torch.cat([p.reshape(-1) for p in params.values(True, True)]) - theta0

    def model_kl():
        return 0.5 * (curvature * delta().pow(2)).sum()

    def closure():  # measured KL is 4x the quadratic model: the first trials must be rejected
        return (c * delta()).sum(), 4 * model_kl()

    info = TRPOStep(params, max_kl=0.01, cg_iters=30, hvp=KLHessian(lambda batch: model_kl()))(closure)
    assert info["accepted"] == 1.0 and info["backtracks"] > 1
    assert info["rejected_kl"] == info["backtracks"] - 1 and info["rejected_surrogate"] == 0  # too far, not worse
    assert 0 < info["kl"] <= 0.01 and info["improvement"] > 0
    step = theta0 - _flat(params)
    # natural-gradient direction: H^{-1} c with H = diag(curvature)
    torch.testing.assert_close(step / step.norm(), (c / curvature) / (c / curvature).norm(), rtol=1e-4, atol=1e-5)
    assert 4 * 0.5 * (curvature * step.pow(2)).sum() <= 0.01 + 1e-6


def test_initial_value_replaces_the_first_closure_call():
    params = _params(2)
    theta0 = _flat(params).clone()
    c = torch.linspace(-1, 1, theta0.numel())
    calls = []

    def closure():
        calls.append(torch.is_grad_enabled())
        delta = torch.cat([p.reshape(-1) for p in params.values(True, True)]) - theta0
        return (c * delta).sum(), 0.5 * delta.pow(2).sum()

    trpo = TRPOStep(params, max_kl=0.01)
    reference = trpo(closure)
    stepped = _flat(params)
    assert calls[0] and not any(calls[1:])  # one graph-building call, then no_grad trials
    with torch.no_grad():
        for p, p0 in zip(params.values(True, True), theta0.split([p.numel() for p in params.values(True, True)])):
            p.copy_(p0.view_as(p))
    calls.clear()
    info = trpo(closure, initial=closure())
    assert len(calls) == 1 + info["backtracks"]  # the given value, then only line-search trials
    untimed = {k: v for k, v in info.items() if not k.endswith("_s")}  # direction_s, cg_s, line_search_s: wall clock
    assert untimed == {k: reference[k] for k in untimed} and torch.equal(_flat(params), stepped)


@pytest.mark.parametrize(
    "kwargs, message",
    [({"max_kl": 0.0}, "max_kl: got 0.0; expected a finite number > 0"),
     ({"max_kl": float("inf")}, "max_kl: got inf; expected a finite number > 0"),
     ({"backtrack_ratio": 1.0}, "backtrack_ratio: got 1.0; expected a finite number in (0, 1)"),
     ({"cg_iters": 0}, "cg_iters: got 0; expected an integer >= 1")],
)
def test_bad_hyperparameters_name_the_argument(kwargs, message):
    params = TensorDict({"w": torch.zeros(2, requires_grad=True)}, [])
    with pytest.raises((TypeError, ValueError), match=re.escape(message)):
        TRPOStep(params, **kwargs)
