"""``learn_std=False`` (maml_rl's ``MAMLGaussianMLPPolicy(learn_std=...)``): the std stays ``init_std`` through
MAML's inner step, its TRPO step and a reloaded checkpoint, while a learned one moves."""
import math

import pytest
import torch
from tensordict import TensorDict

from umrl.checkpoints import load_maml_checkpoint, load_maml_policy
from umrl.configs import ConfigError
from umrl.modules import policy_log_std
from umrl.modules.policy import make_gaussian_policy, std_is_fixed
from umrl.objectives.maml import MAMLLoss
from umrl.rollout import FunctionalPolicy
from umrl.trainers import compose
from umrl.trainers.maml import train

T, N, H, OBS, ACT = 2, 3, 4, 2, 2
TINY = ["env.horizon=10", "meta_batch_size=2", "trajectories_per_task=3", "policy.hidden=[16]", "policy.init_std=0.5",
        "logger.backend=none", "progress=false", "checkpoint.every=1", "trpo.cg_iters=3", "iterations=2"]


def _batch(policy, seed):
    """A [T, N, H] support batch with actions drawn from ``policy``."""
    g = torch.Generator().manual_seed(seed)
    td = TensorDict({"observation": torch.randn(T, N, H, OBS, generator=g),
                     "advantage": torch.randn(T, N, H, 1, generator=g),
                     "mask": torch.ones(T, N, H, dtype=torch.bool)}, batch_size=[T, N, H])
    with torch.no_grad():
        td.update(FunctionalPolicy(policy).dist_params(TensorDict.from_module(policy).detach(), td))
    td["action"] = td["loc"] + td["scale"] * torch.randn(td["loc"].shape, generator=g)
    return td


@pytest.mark.parametrize("learn_std", [True, False])
def test_inner_step_and_meta_gradient_move_only_a_learned_std(learn_std):
    policy = make_gaussian_policy(OBS, ACT, hidden=(8,), init_std=0.7, learn_std=learn_std, seed=0)
    learned = make_gaussian_policy(OBS, ACT, hidden=(8,), init_std=0.7, seed=0)
    assert std_is_fixed(policy) is not learn_std and not std_is_fixed(learned)
    assert list(policy.state_dict()) == list(learned.state_dict())  # same keys: checkpoints and MAML need no case
    loss = MAMLLoss(policy, inner_lr=0.5)
    support = _batch(policy, seed=1)
    assert torch.allclose(support["scale"], torch.full_like(support["scale"], 0.7))
    adapted = loss.adapt(support)  # second order, differentiable in θ
    key = next(k for k in adapted.keys(True, True) if k[-1] == "state_independent_scale")
    moved = (adapted.get(key) - math.log(0.7)).abs().max().item()
    query = _batch(policy, seed=2)
    log_lik = FunctionalPolicy(policy).log_prob(adapted, query).sum()  # the meta-objective's term, through the step
    meta_grad, mean_grad = torch.autograd.grad(log_lik, [policy_log_std(policy), next(policy.parameters())])
    if learn_std:
        assert moved > 1e-3 and meta_grad.abs().max() > 0
    else:
        assert moved == 0 and torch.equal(meta_grad, torch.zeros_like(meta_grad))
    assert mean_grad.abs().max() > 0  # the mean network learns either way


def test_meta_training_keeps_a_fixed_std_and_reloads_it(tmp_path):
    train(compose("maml", [*TINY, f"output_dir={tmp_path}", "policy.learn_std=false"]))
    state = load_maml_checkpoint(tmp_path)
    assert state["meta"]["learn_std"] is False
    policy, _ = load_maml_policy(tmp_path)
    assert std_is_fixed(policy)
    assert torch.allclose(policy_log_std(policy), torch.full((2,), math.log(0.5)))
    start = load_maml_checkpoint(tmp_path / "checkpoints" / "step_0.safetensors")["policy"]
    moved = {k for k in start if not torch.equal(start[k], state["policy"][k])}
    assert moved and not any(k.endswith("state_independent_scale") for k in moved)  # the mean network learned

def test_a_fixed_std_refuses_the_hand_derived_product(tmp_path):
    with pytest.raises(ConfigError, match="trpo.hvp: got 'analytic'.*gauss_newton or exact with policy.learn_std=false"):
        train(compose("maml", [*TINY, f"output_dir={tmp_path}", "policy.learn_std=false", "trpo.hvp=analytic"]))


def test_second_step_diagnostic_reports_the_std_each_batch_was_collected_with(tmp_path, tiny_maml_run):
    """scripts/diagnostics/second_step.py's log σ column: the adapted policies' std moves with a learned std and
    stays at ``init_std`` with a fixed one."""
    from script_loading import load_script

    from umrl.envs.tasks import get_task_family
    from umrl.metatest import AdaptationConfig

    train(compose("maml", [*TINY, f"output_dir={tmp_path / 'fixed'}", "policy.learn_std=false"]))
    diagnostic = load_script("scripts/diagnostics/second_step.py")
    config = AdaptationConfig(num_steps=2, num_trajectories=3, horizon=10, sgd_schedule="reference")
    tasks = get_task_family("point_nav").eval_tasks(2)
    runs = {name: diagnostic.adapt(str(run), env_name="point_nav", tasks=tasks, seed=1, config=config)
            for name, run in (("learned", tiny_maml_run), ("fixed", tmp_path / "fixed"))}
    learned, fixed = runs["learned"]["log_std"], runs["fixed"]["log_std"]
    assert learned.shape == fixed.shape == (3, 2)
    assert abs(learned[0] - policy_log_std(load_maml_policy(tiny_maml_run)[0]).mean().item()).max() < 1e-6
    assert abs(learned[1:] - learned[0]).min() > 0
    assert abs(fixed - math.log(0.5)).max() < 1e-6
