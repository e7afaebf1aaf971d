"""Bayes-by-backprop dynamics model ``(s, a) -> s'`` and VIME's information gain.

VIME (Houthooft et al., 2016, https://arxiv.org/abs/1605.09674) rewards a transition by how much it would move a
Bayesian dynamics model. This module holds the model and the maths:

- :class:`BayesianLinear`: factorised Gaussian weights ``w ~ N(mu, sigma^2)``, ``sigma = softplus(rho)``.
- :class:`BayesianDynamics`: an MLP of Bayesian layers (one hidden layer of 32 ReLU units by default) from the
  standardised ``(observation, action)`` to the standardised next observation, with a Gaussian likelihood of fixed
  std, a factorised Gaussian prior ``N(0, prior_std^2)`` and running input/target statistics.
- :meth:`BayesianDynamics.info_gain`: for every transition of a batch at once (``torch.func.vmap`` over
  ``torch.func.grad``), the KL between the posterior after one second-order step on that transition and the
  current posterior, with the diagonal Hessian of that KL in ``(mu, rho)``.

The ELBO loss lives in :class:`umrl.objectives.vime.VIMELoss`; the reward transform in
:class:`umrl.transforms.vime_bonus.VIMEBonus`.
"""
from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn
from torch.distributions import Normal, kl_divergence
from torch.func import functional_call, grad, vmap
from torchrl.envs.transforms.rnd import RunningMeanStd

from umrl.validation import check_positive

Noise = list[tuple[torch.Tensor, torch.Tensor]]


def softplus_inverse(x: float) -> float:
    """``rho`` such that ``softplus(rho) == x`` (``x > 0``)."""
    if x <= 0:
        raise ValueError(f"softplus_inverse needs a positive std, got {x}.")
    return x + math.log(-math.expm1(-x))


def gaussian_kl(
    mu_q: torch.Tensor, std_q: torch.Tensor, mu_p: torch.Tensor | float, std_p: torch.Tensor | float
) -> torch.Tensor:
    """Closed-form ``KL(N(mu_q, std_q^2) || N(mu_p, std_p^2))`` summed over all elements (a scalar)."""
    return kl_divergence(Normal(mu_q, std_q, validate_args=False), Normal(mu_p, std_p, validate_args=False)).sum()


class BayesianLinear(nn.Module):
    """Linear layer with factorised Gaussian weights and biases.

    Parameters: ``weight_mu``, ``weight_rho`` ``[out, in]``; ``bias_mu``, ``bias_rho`` ``[out]``. The std is
    ``softplus(rho)``. Means start like ``nn.Linear``'s weights (uniform in ``±1/sqrt(in)``, biases 0), stds at
    ``init_std``.

    ``forward(x [S, N, in], weight_noise [S, out, in], bias_noise [S, out]) -> [S, N, out]`` uses one weight sample
    per leading index ``S`` (shared by the ``N`` inputs); the noise is passed in so that callers control it (the
    same draw can serve a whole vmapped batch). A single input per sample, ``x [S, in] -> [S, out]``, is computed
    by broadcasting instead of a batched matmul: under ``vmap`` over transitions that makes the per-sample weight
    gradients elementwise products, measured 2x faster than the ``k = 1`` batched matmuls on CPU.
    """

    def __init__(self, in_features: int, out_features: int, *, init_std: float):
        super().__init__()
        bound = 1.0 / math.sqrt(in_features)
        self.weight_mu = nn.Parameter(torch.empty(out_features, in_features).uniform_(-bound, bound))
        self.weight_rho = nn.Parameter(torch.full((out_features, in_features), softplus_inverse(init_std)))
        self.bias_mu = nn.Parameter(torch.zeros(out_features))
        self.bias_rho = nn.Parameter(torch.full((out_features,), softplus_inverse(init_std)))

    def forward(self, x: torch.Tensor, weight_noise: torch.Tensor, bias_noise: torch.Tensor) -> torch.Tensor:
        weight = self.weight_mu + F.softplus(self.weight_rho) * weight_noise
        bias = self.bias_mu + F.softplus(self.bias_rho) * bias_noise
        if x.dim() == 2:
            return (weight * x.unsqueeze(-2)).sum(-1) + bias
        return torch.baddbmm(bias.unsqueeze(-2), x, weight.transpose(-1, -2))


class BayesianDynamics(nn.Module):
    """Bayesian neural network ``(s, a) -> s'`` trained by Bayes by backprop (VIME's dynamics model).

    Args:
        obs_dim (int): observation size ``D``.
        act_dim (int): action size ``A``.

    Keyword Args:
        hidden (sequence of int): hidden layer widths, ReLU between layers. Default ``(32,)``.
        prior_std (float): std of the factorised prior ``N(0, prior_std^2)`` on every weight. Default 0.5.
        likelihood_std (float): std of the Gaussian likelihood of the *standardised* next observation. Default 0.5.
        init_std (float | None): initial posterior std; ``None`` uses ``prior_std`` (VIME's choice).

    Shapes: ``obs [N, D]``, ``action [N, A]``, ``next_obs [N, D]``; standardised inputs ``x [N, D + A]`` and
    targets ``y [N, D]``; noise from :meth:`sample_noise`; ``forward(x, noise) -> [S, N, D]`` predicted means of the
    standardised next observation, one per weight sample.

    Inputs and targets are standardised with running statistics (:class:`torchrl.envs.transforms.rnd.RunningMeanStd`,
    buffers ``input_rms`` / ``target_rms``) that only :meth:`update_normalizer` changes.

    Examples:
        >>> bnn = BayesianDynamics(2, 2)
        >>> obs, act, nxt = torch.randn(64, 2), torch.randn(64, 2), torch.randn(64, 2)
        >>> bnn.update_normalizer(obs, act, nxt)
        >>> bnn.info_gain(obs, act, nxt).shape
        torch.Size([64])
    """

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        *,
        hidden: Sequence[int] = (32,),
        prior_std: float = 0.5,
        likelihood_std: float = 0.5,
        init_std: float | None = None,
    ):
        super().__init__()
        if obs_dim < 1 or act_dim < 1:
            raise ValueError(f"obs_dim and act_dim must be positive, got {obs_dim} and {act_dim}.")
        check_positive("prior_std", prior_std)
        check_positive("likelihood_std", likelihood_std)
        if init_std is not None:  # None: prior_std
            check_positive("init_std", init_std)
        self.obs_dim, self.act_dim = obs_dim, act_dim
        self.prior_std = float(prior_std)
        self.likelihood_std = float(likelihood_std)
        sizes = [obs_dim + act_dim, *hidden, obs_dim]
        std0 = self.prior_std if init_std is None else float(init_std)
        self.layers = nn.ModuleList(
            BayesianLinear(i, o, init_std=std0) for i, o in itertools.pairwise(sizes)
        )
        self.input_rms = RunningMeanStd(shape=(obs_dim + act_dim,))
        self.target_rms = RunningMeanStd(shape=(obs_dim,))

    # ----------------------------------------------------------------- data
    @torch.no_grad()
    def update_normalizer(self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor) -> None:
        """Fold a batch of transitions into the running input / target statistics."""
        self.input_rms.update(torch.cat([obs, action], -1))
        self.target_rms.update(next_obs)

    def normalize(
        self, obs: torch.Tensor, action: torch.Tensor, next_obs: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Standardised ``x = (s, a)`` ``[N, D + A]`` and ``y = s'`` ``[N, D]``."""
        if obs.shape[-1] != self.obs_dim or action.shape[-1] != self.act_dim or next_obs.shape[-1] != self.obs_dim:
            raise ValueError(
                f"expected obs/next_obs [..., {self.obs_dim}] and action [..., {self.act_dim}], got "
                f"{tuple(obs.shape)}, {tuple(next_obs.shape)}, {tuple(action.shape)}."
            )
        x = self.input_rms.normalize(torch.cat([obs, action], -1))
        return x, self.target_rms.normalize(next_obs)

    # ---------------------------------------------------------------- model
    def sample_noise(self, num_samples: int, generator: torch.Generator | None = None) -> Noise:
        """Standard-normal noise for ``num_samples`` weight draws: per layer ``([S, out, in], [S, out])``."""
        device = self.layers[0].weight_mu.device
        return [
            (
                torch.randn(num_samples, *layer.weight_mu.shape, generator=generator, device=device),
                torch.randn(num_samples, *layer.bias_mu.shape, generator=generator, device=device),
            )
            for layer in self.layers
        ]

    def forward(self, x: torch.Tensor, noise: Noise) -> torch.Tensor:
        """Predicted standardised next observation, ``x [N, D + A]`` -> ``[S, N, D]`` (one input ``[D + A]`` ->
        ``[S, D]``)."""
        h = x.expand(noise[0][0].shape[0], *x.shape)
        for i, (layer, (w_eps, b_eps)) in enumerate(zip(self.layers, noise)):
            h = layer(h, w_eps, b_eps)
            if i < len(self.layers) - 1:
                h = torch.relu(h)
        return h

    def log_likelihood(self, x: torch.Tensor, y: torch.Tensor, noise: Noise) -> torch.Tensor:
        """``log N(y; f_theta(x), likelihood_std^2)`` summed over dims, per weight sample: ``[S, N]``."""
        return self.gaussian_log_prob(self(x, noise), y)

    def gaussian_log_prob(self, pred: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """Likelihood of targets ``y [N, D]`` under predictions ``pred [S, N, D]``: ``[S, N]``."""
        var = self.likelihood_std**2
        return -0.5 * (((y - pred) ** 2) / var + math.log(2 * math.pi * var)).sum(-1)

    def kl_to_prior(self) -> torch.Tensor:
        """Closed-form ``KL(q(theta) || N(0, prior_std^2))`` over all weights (scalar, differentiable)."""
        return self.kl_between(dict(self.named_parameters()), None)

    def kl_between(self, params_q: dict[str, torch.Tensor], params_p: dict[str, torch.Tensor] | None) -> torch.Tensor:
        """Closed-form ``KL(q(params_q) || q(params_p))``; ``params_p=None`` means the prior. Keys as ``named_parameters``."""
        total = torch.zeros((), device=next(iter(params_q.values())).device)
        for name, mu_q in params_q.items():
            if not name.endswith("_mu"):
                continue
            rho = name[: -len("_mu")] + "_rho"
            std_q = F.softplus(params_q[rho])
            if params_p is None:
                total = total + gaussian_kl(mu_q, std_q, 0.0, self.prior_std)
            else:
                total = total + gaussian_kl(mu_q, std_q, params_p[name], F.softplus(params_p[rho]))
        return total

    @staticmethod
    def inverse_kl_hessian(params: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """Inverse diagonal Hessian of ``KL(q(phi') || q(phi))`` in ``phi' = (mu, rho)`` at ``phi' = phi``.

        ``H_mu = 1 / sigma^2`` and ``H_rho = 2 sigmoid(rho)^2 / sigma^2`` with ``sigma = softplus(rho)``.
        """
        inv_h = {}
        for name, value in params.items():
            rho = params[name[: -len("_mu")] + "_rho"] if name.endswith("_mu") else value
            var = F.softplus(rho) ** 2
            inv_h[name] = var if name.endswith("_mu") else var / (2.0 * torch.sigmoid(rho) ** 2)
        return inv_h

    # ------------------------------------------------------- information gain
    def info_gain(
        self,
        obs: torch.Tensor,
        action: torch.Tensor,
        next_obs: torch.Tensor,
        *,
        num_samples: int = 10,
        step_size: float = 0.01,
        noise: Noise | None = None,
        chunk_size: int | None = None,
    ) -> torch.Tensor:
        """Per-transition information gain ``[N]`` (nats), second-order approximation.

        For transition ``n`` with ``g_n = grad_phi [-mean_s log p(s'_n | s_n, a_n, theta_s)]``, one second-order
        step ``phi'_n = phi - step_size * H^{-1} g_n`` (``H``: diagonal Hessian of the KL between posteriors, see
        :meth:`inverse_kl_hessian`) moves the posterior by
        ``KL(q(phi'_n) || q(phi)) ~= 0.5 * step_size^2 * sum_k g_nk^2 / H_k``.
        All ``N`` gradients come from one ``vmap(grad(...))``; the ``num_samples`` weight draws (``noise``) are
        shared across the batch. ``chunk_size`` bounds the memory of the vmap (default: about 2^25 floats of
        per-sample gradients per chunk: the whole batch for point_nav, a few hundred transitions for Ant). Uses
        the current normalizer.
        """
        x, y = self.normalize(obs, action, next_obs)
        params = {k: v.detach() for k, v in self.named_parameters()}
        inv_h = self.inverse_kl_hessian(params)
        if noise is None:
            noise = self.sample_noise(num_samples)
        if chunk_size is None:
            num_weights = sum(v.numel() for v in params.values())
            chunk_size = max(1, 2**25 // (noise[0][0].shape[0] * num_weights))

        def nll(p: dict[str, torch.Tensor], xi: torch.Tensor, yi: torch.Tensor) -> torch.Tensor:
            pred = functional_call(self, p, (xi, noise))  # [S, D]
            return -self.gaussian_log_prob(pred, yi).mean()

        def kl_after_step(xi: torch.Tensor, yi: torch.Tensor) -> torch.Tensor:
            g = grad(nll)(params, xi, yi)
            return 0.5 * step_size**2 * sum((g[k] ** 2 * inv_h[k]).sum() for k in g)

        return vmap(kl_after_step, chunk_size=chunk_size)(x.detach(), y.detach())
