"""The maths of VIME's Bayesian dynamics model: KLs, the diagonal Hessian, the information gain."""
import math

import pytest
import torch
import torch.nn.functional as F

from umrl.modules.bnn import BayesianDynamics, gaussian_kl, softplus_inverse


def _tiny(seed=0, **kwargs):
    torch.manual_seed(seed)
    bnn = BayesianDynamics(2, 1, hidden=(4,), **kwargs)
    obs, act = torch.randn(64, 2), torch.randn(64, 1)
    bnn.update_normalizer(obs, act, obs + 0.1 * act)
    with torch.no_grad():  # a posterior that is not the initial one
        for name, p in bnn.named_parameters():
            p.add_(0.3 * torch.randn_like(p)) if name.endswith("_rho") else p.add_(0.1 * torch.randn_like(p))
    return bnn


def _nll(bnn, obs, act, nxt, noise):
    x, y = bnn.normalize(obs, act, nxt)
    return -bnn.log_likelihood(x, y, noise).mean()


def test_softplus_inverse():
    assert F.softplus(torch.tensor(softplus_inverse(0.37))).item() == pytest.approx(0.37, rel=1e-6)
    with pytest.raises(ValueError, match="positive"):
        softplus_inverse(0.0)


def test_closed_form_kl_matches_monte_carlo():
    g = torch.Generator().manual_seed(0)
    mu_q, std_q = torch.randn(5, generator=g), 0.2 + torch.rand(5, generator=g)
    mu_p, std_p = torch.randn(5, generator=g), 0.5 + torch.rand(5, generator=g)
    q, p = torch.distributions.Normal(mu_q, std_q), torch.distributions.Normal(mu_p, std_p)
    w = q.sample((400_000,))
    mc = (q.log_prob(w) - p.log_prob(w)).sum(-1).mean()
    closed = gaussian_kl(mu_q, std_q, mu_p, std_p)
    assert closed.item() == pytest.approx(mc.item(), rel=0.02)
    assert closed.item() == pytest.approx(torch.distributions.kl_divergence(q, p).sum().item(), rel=1e-5)


def test_kl_to_prior_matches_monte_carlo_over_weights():
    bnn = _tiny()
    mc = []
    for name, mu in bnn.named_parameters():
        if name.endswith("_mu"):
            std = F.softplus(dict(bnn.named_parameters())[name[:-3] + "_rho"]).detach()
            q, p = torch.distributions.Normal(mu.detach(), std), torch.distributions.Normal(0.0, bnn.prior_std)
            w = q.sample((100_000,))
            mc.append((q.log_prob(w) - p.log_prob(w)).flatten(1).sum(-1).mean())
    assert bnn.kl_to_prior().item() == pytest.approx(sum(mc).item(), rel=0.02)


def test_inverse_hessian_matches_autograd_hessian_of_kl():
    mu, rho = torch.randn(3), torch.randn(3)

    def kl(mu_new, rho_new):
        return gaussian_kl(mu_new, F.softplus(rho_new), mu, F.softplus(rho))

    h_mu, h_rho = (torch.autograd.functional.hessian(kl, (mu, rho))[i][i].diagonal() for i in (0, 1))
    inv_h = BayesianDynamics.inverse_kl_hessian({"w_mu": mu, "w_rho": rho})
    torch.testing.assert_close(inv_h["w_mu"], 1 / h_mu)
    torch.testing.assert_close(inv_h["w_rho"], 1 / h_rho)


@pytest.mark.parametrize("step_size", [1e-3, 1e-2])
def test_info_gain_matches_exact_kl_after_explicit_second_order_step(step_size):
    bnn = _tiny()
    obs, act, nxt = torch.randn(1, 2), torch.randn(1, 1), torch.randn(1, 2)
    noise = bnn.sample_noise(10, generator=torch.Generator().manual_seed(1))
    params = dict(bnn.named_parameters())
    grads = dict(zip(params, torch.autograd.grad(_nll(bnn, obs, act, nxt, noise), list(params.values()))))
    inv_h = bnn.inverse_kl_hessian({k: v.detach() for k, v in params.items()})
    updated = {k: (v - step_size * inv_h[k] * grads[k]).detach() for k, v in params.items()}
    exact = bnn.kl_between(updated, {k: v.detach() for k, v in params.items()})
    approx = bnn.info_gain(obs, act, nxt, noise=noise, step_size=step_size)
    assert exact.item() > 0
    assert approx.item() == pytest.approx(exact.item(), rel=2 * step_size)


def test_batched_info_gain_equals_per_transition_loop():
    bnn = _tiny(seed=3)
    obs, act, nxt = torch.randn(7, 2), torch.randn(7, 1), torch.randn(7, 2)
    noise = bnn.sample_noise(4, generator=torch.Generator().manual_seed(2))
    params = dict(bnn.named_parameters())
    inv_h = bnn.inverse_kl_hessian({k: v.detach() for k, v in params.items()})
    loop = []
    for i in range(7):
        g = torch.autograd.grad(_nll(bnn, obs[i : i + 1], act[i : i + 1], nxt[i : i + 1], noise), list(params.values()))
        loop.append(0.5 * 0.01**2 * sum((gi**2 * inv_h[k]).sum() for k, gi in zip(params, g)))
    batched = bnn.info_gain(obs, act, nxt, noise=noise)
    torch.testing.assert_close(batched, torch.stack(loop), rtol=1e-4, atol=1e-12)
    torch.testing.assert_close(bnn.info_gain(obs, act, nxt, noise=noise, chunk_size=3), batched)


def test_normalizer_standardises_and_rejects_bad_shapes():
    bnn = BayesianDynamics(3, 2)
    obs, act = 5 + 3 * torch.randn(5000, 3), torch.randn(5000, 2)
    bnn.update_normalizer(obs, act, 2 * obs)
    x, y = bnn.normalize(obs, act, 2 * obs)
    torch.testing.assert_close(x.mean(0), torch.zeros(5), atol=1e-3, rtol=0)
    torch.testing.assert_close(y.std(0), torch.ones(3), atol=1e-2, rtol=0)
    with pytest.raises(ValueError, match="expected obs"):
        bnn.normalize(obs, act[:, :1], obs)
    with pytest.raises(ValueError, match=r"prior_std: got 0.0; expected a finite number > 0"):
        BayesianDynamics(3, 2, prior_std=0.0)


def test_forward_shapes_and_initial_std():
    bnn = BayesianDynamics(4, 2, hidden=(32,), prior_std=0.5)
    out = bnn(torch.randn(9, 6), bnn.sample_noise(10))
    assert out.shape == (10, 9, 4)
    assert F.softplus(bnn.layers[0].weight_rho).mean().item() == pytest.approx(0.5)
    assert len(bnn.layers) == 2 and bnn.layers[0].weight_mu.shape == (32, 6)
    assert bnn.kl_to_prior().item() == pytest.approx(
        0.5 * sum((p**2).sum().item() for n, p in bnn.named_parameters() if n.endswith("_mu")) / 0.25, rel=1e-4
    )
    assert math.isfinite(bnn.kl_to_prior().item())
