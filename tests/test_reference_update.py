"""The meta-test update against a line-by-line transcription of the MAML reference code's test-time VPG.

cbfinn/maml_rl ``maml_examples/test_maml_point.py`` adapts the loaded policy with ``sandbox/rocky/tf/algos/vpg.py``
(``FirstOrderOptimizer``: ``GradientDescentOptimizer``, the whole batch, one step per iteration, ``init_learning_rate``
α for the first step and ``learning_rate`` α/2 after) on samples processed by ``rllab/sampler/base.py``
(``process_samples``: discounted returns, ``LinearFeatureBaseline`` fitted on this batch *before* the advantages,
GAE, ``center_adv`` over the whole batch). The policy is ``MAMLGaussianMLPPolicy``: ``relu(x W + b)`` layers, an
identity output and a state-independent ``log_std = max(std_param, log 1e-6)``.

The transcription below works on the reference's data layout (a list of paths, each cut at its own end) in float64
and is compared with :class:`umrl.metatest.TaskAdapter` on the same recorded batch: loss, gradient and new
parameters, for the first (α) and the second (α/2) update, and the recorded mean return.
"""
import math

import numpy as np
import pytest
import torch

from umrl.metatest import AdaptationConfig, TaskAdapter, make_eval_env
from umrl.modules.policy import make_gaussian_policy
from umrl.objectives.policy_gradient import episode_returns

GOALS = torch.tensor([[0.03, -0.02], [-0.01, 0.02]])  # near the start: some episodes reach the goal and end early
HIDDEN = (16, 16)
ALPHA = 0.5
DISCOUNT, GAE_LAMBDA = 0.99, 1.0  # BatchPolopt's defaults, which test_maml_point.py keeps
MIN_STD = 1e-6  # MAMLGaussianMLPPolicy's default min_std
# umrl parameter name -> the reference's (MAMLGaussianMLPPolicy.all_params); weights are [in, out] there
PARAM_NAMES = {
    "module.0.module.0.0.weight": "W0", "module.0.module.0.0.bias": "b0",
    "module.0.module.0.2.weight": "W1", "module.0.module.0.2.bias": "b1",
    "module.0.module.0.4.weight": "W2", "module.0.module.0.4.bias": "b2",
    "module.0.module.1.state_independent_scale": "std_param",
}


# --- rllab/misc/special.py -------------------------------------------------------------------------------------------
def discount_cumsum(x, discount):
    # scipy.signal.lfilter([1], [1, -discount], x[::-1])[::-1]: y[t] = x[t] + discount * y[t + 1]
    y = np.zeros_like(x)
    running = 0.0
    for t in reversed(range(len(x))):
        running = x[t] + discount * running
        y[t] = running
    return y


# --- rllab/baselines/linear_feature_baseline.py ---------------------------------------------------------------------
class LinearFeatureBaseline:
    def __init__(self, reg_coeff=1e-5):
        self._coeffs = None
        self._reg_coeff = reg_coeff

    def _features(self, path):
        o = np.clip(path["observations"], -10, 10)
        length = len(path["rewards"])
        al = np.arange(length).reshape(-1, 1) / 100.0
        return np.concatenate([o, o ** 2, al, al ** 2, al ** 3, np.ones((length, 1))], axis=1)

    def fit(self, paths):
        featmat = np.concatenate([self._features(path) for path in paths])
        returns = np.concatenate([path["returns"] for path in paths])
        reg_coeff = self._reg_coeff
        for _ in range(5):
            self._coeffs = np.linalg.lstsq(
                featmat.T.dot(featmat) + reg_coeff * np.identity(featmat.shape[1]), featmat.T.dot(returns), rcond=None
            )[0]
            if not np.any(np.isnan(self._coeffs)):
                break
            reg_coeff *= 10

    def predict(self, path):
        return self._features(path).dot(self._coeffs)


# --- rllab/sampler/base.py: BaseSampler.process_samples (non-recurrent branch) --------------------------------------
def process_samples(paths, baseline, center_adv=True):
    for path in paths:
        path["returns"] = discount_cumsum(path["rewards"], DISCOUNT)
    baseline.fit(paths)  # maml_rl fits on this batch before computing its advantages
    all_path_baselines = [baseline.predict(path) for path in paths]
    for idx, path in enumerate(paths):
        path_baselines = np.append(all_path_baselines[idx], 0)
        deltas = path["rewards"] + DISCOUNT * path_baselines[1:] - path_baselines[:-1]
        path["advantages"] = discount_cumsum(deltas, DISCOUNT * GAE_LAMBDA)
    observations = np.concatenate([path["observations"] for path in paths])
    actions = np.concatenate([path["actions"] for path in paths])
    advantages = np.concatenate([path["advantages"] for path in paths])
    if center_adv:  # rllab/algos/util.py: center_advantages
        advantages = (advantages - np.mean(advantages)) / (advantages.std() + 1e-8)
    average_return = np.mean([sum(path["rewards"]) for path in paths])  # logged as AverageReturn
    return {"observations": observations, "actions": actions, "advantages": advantages}, average_return


# --- sandbox/rocky/tf/policies/maml_minimal_gauss_mlp_policy.py + distributions/diagonal_gaussian.py ------------------
def dist_info(params, obs):
    hidden = obs
    for i in range(len(HIDDEN)):
        hidden = torch.relu(hidden @ params[f"W{i}"] + params[f"b{i}"])  # forward_dense_layer, relu
    mean = hidden @ params[f"W{len(HIDDEN)}"] + params[f"b{len(HIDDEN)}"]  # output_nonlinearity = identity
    log_std = torch.maximum(params["std_param"], torch.tensor(math.log(MIN_STD), dtype=obs.dtype))
    return mean, log_std.expand_as(mean)


def log_likelihood(x, mean, log_std):
    zs = (x - mean) / torch.exp(log_std)
    return -log_std.sum(-1) - 0.5 * zs.square().sum(-1) - 0.5 * x.shape[-1] * np.log(2 * np.pi)


# --- sandbox/rocky/tf/algos/vpg.py (init_opt, non-recurrent) + optimizers/first_order_optimizer.py -------------------
class ReferenceVPG:
    """``surr_obj = -reduce_mean(logli * advantage)``, minimised by plain gradient descent on the whole batch, one
    step per iteration: ``init_learning_rate`` for the first run of the train op, ``learning_rate`` afterwards."""

    def __init__(self, params, init_learning_rate, learning_rate):
        self.params = {k: v.clone() for k, v in params.items()}
        self._init_lr, self._lr = init_learning_rate, learning_rate

    def surr_obj(self, samples):
        obs, actions, adv = (torch.as_tensor(samples[k]) for k in ("observations", "actions", "advantages"))
        mean, log_std = dist_info(self.params, obs)
        return -(log_likelihood(actions, mean, log_std) * adv).mean()

    def optimize(self, samples):
        leaves = {k: v.clone().requires_grad_() for k, v in self.params.items()}
        self.params = leaves
        loss = self.surr_obj(samples)
        grads = dict(zip(leaves, torch.autograd.grad(loss, list(leaves.values())), strict=True))
        lr = self._init_lr if self._init_lr is not None else self._lr
        self._init_lr = None  # "only use it once"
        self.params = {k: (v - lr * grads[k]).detach() for k, v in leaves.items()}
        return loss.detach(), grads


def reference_params(params_td, task):
    """The reference's parameter dict (float64, weights [in, out]) from umrl's per-task parameters."""
    flat = params_td[task].flatten_keys(".")
    return {ref: (flat[name].detach().double().T if ref.startswith("W") else flat[name].detach().double())
            for name, ref in PARAM_NAMES.items()}


def reference_paths(batch, task):
    """The reference's paths of one task: each trajectory cut after its first episode (rllab's rollout stops at
    ``done``)."""
    paths = []
    for n in range(batch.shape[1]):
        length = int(batch["mask"][task, n].sum())
        paths.append({"observations": batch["observation"][task, n, :length].double().numpy(),
                          "actions": batch["action"][task, n, :length].double().numpy(),
                          "rewards": batch["next", "reward"][task, n, :length, 0].double().numpy()})
    return paths


def test_umrl_meta_test_update_equals_the_reference_vpg_step():
    torch.manual_seed(3)
    horizon, trajectories = 40, 12
    policy = make_gaussian_policy(2, 2, hidden=HIDDEN, init_std=0.3)
    config = AdaptationConfig(num_steps=2, num_trajectories=trajectories, horizon=horizon, sgd_schedule="reference")
    env = make_eval_env("point_nav", GOALS, trajectories, seed=0, horizon=horizon)
    adapter = TaskAdapter(policy, env, len(GOALS), optimizer="sgd", lr=ALPHA, config=config)
    references = [ReferenceVPG(reference_params(adapter.params, t), ALPHA, 0.5 * ALPHA) for t in range(len(GOALS))]
    ended_early = 0
    for step in range(2):  # the α step, then an α/2 step on a batch from the adapted policy
        batch = adapter.collect()
        ended_early += int((batch["mask"].sum(-1) < horizon).sum())
        returns = episode_returns(batch).mean(-1)
        losses = adapter.step(batch)
        grads = {name: p.grad for name, p in adapter.params.flatten_keys(".").items()}  # the update's gradient
        for t, reference in enumerate(references):
            samples, average_return = process_samples(reference_paths(batch, t), LinearFeatureBaseline())
            ref_loss, ref_grads = reference.optimize(samples)
            assert returns[t].item() == pytest.approx(average_return, rel=1e-6)
            torch.testing.assert_close(losses[t].double(), ref_loss, rtol=1e-5, atol=1e-6)
            new = reference_params(adapter.params, t)
            for name, ref in PARAM_NAMES.items():
                grad = grads[name][t].double()
                torch.testing.assert_close(grad.T if ref.startswith("W") else grad, ref_grads[ref],
                                           rtol=1e-4, atol=1e-6, msg=lambda m, s=step, r=ref: f"step {s} {r}: {m}")
                torch.testing.assert_close(new[ref], reference.params[ref], rtol=1e-5, atol=1e-6,
                                           msg=lambda m, s=step, r=ref: f"step {s} {r}: {m}")
    env.close()
    assert ended_early > 0  # the batch exercises trajectories of different lengths
