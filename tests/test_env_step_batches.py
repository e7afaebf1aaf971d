"""Meta-test batches of a fixed number of env steps (``protocol.env_steps``, the MAML reference code's sampler):
which episodes are kept, how many rounds run, the returns averaged over the kept episodes, and the bad values."""
from unittest import mock

import pytest
import torch
from script_loading import compose_config
from tensordict import TensorDict

from umrl.configs import ConfigError, validate
from umrl.configs.maml import MAMLConfig
from umrl.configs.suite import SuiteConfig
from umrl.metatest import AdaptationConfig, TaskAdapter, make_eval_env
from umrl.modules.policy import make_gaussian_policy
from umrl.objectives.policy_gradient import episode_mean, episode_returns
from umrl.rollout import collect_env_steps, first_env_steps
from umrl.trajectories import pack_valid_steps

NEAR = torch.tensor([[0.2, 0.0], [0.4, 0.0]])  # on the straight policy's path: its episodes end after 4 and 8 steps
FAR = torch.tensor([[5.0, 5.0], [-5.0, 5.0]])  # out of reach in the horizon: every episode runs to the end


def _straight_policy():
    """Moves (almost deterministically) 0.05 along x per step: zero weights, output bias (0.5, 0), tiny std."""
    policy = make_gaussian_policy(2, 2, hidden=(8,), init_std=1e-4)
    with torch.no_grad():
        for name, p in policy.named_parameters():
            if "scale" not in name:
                p.zero_()
        [*_, last] = [m for m in policy.modules() if isinstance(m, torch.nn.Linear)]
        last.bias.copy_(torch.tensor([0.5, 0.0]))
    return policy


def _batch_with_lengths(lengths: list[list[int]], horizon: int = 10) -> TensorDict:
    mask = torch.arange(horizon) < torch.tensor(lengths).unsqueeze(-1)  # [T, M, H]
    index = torch.arange(mask[..., 0].numel()).reshape(*mask.shape[:2], 1).expand(mask.shape)
    return TensorDict({"mask": mask, "index": index}, batch_size=mask.shape)


def test_first_env_steps_keeps_each_tasks_first_episodes_until_the_budget_the_last_whole():
    batch = first_env_steps(_batch_with_lengths([[10, 10, 10, 10], [3, 2, 10, 1]]), env_steps=12)
    # task 0: 0 and 10 steps precede episodes 0 and 1 (< 12), 20 precede episode 2; task 1: 0, 3, 5 < 12, then 15
    assert batch.shape == (2, 3, 10)
    assert batch["mask"].sum(-1).tolist() == [[10, 10, 0], [3, 2, 10]]
    assert batch["index"][..., 0].tolist() == [[0, 1, 2], [4, 5, 6]]  # trajectories keep their order; the 4th is dropped


def test_collect_env_steps_reaches_every_tasks_budget_with_more_episodes_where_they_end_early():
    horizon, per_round, budget = 20, 4, 30
    env = make_eval_env("point_nav", torch.cat([NEAR, FAR[:1]]), per_round, seed=0, horizon=horizon)
    batch = collect_env_steps(env, _straight_policy(), num_tasks=3, horizon=horizon, env_steps=budget)
    env.close()
    # 4-step episodes: 8 of them (28 steps before the 8th); 8-step: 4 (24 before the 4th); 20-step: 2 (20 before)
    assert batch.shape == (3, 8, horizon)  # two rounds of 4 were needed for the first task
    assert batch["mask"].sum(-1).tolist() == [[4] * 8, [8] * 4 + [0] * 4, [20] * 2 + [0] * 6]
    with pytest.raises(ValueError, match=r"env_steps: got 0; expected an integer >= 1"):
        collect_env_steps(env, _straight_policy(), num_tasks=3, horizon=horizon, env_steps=0)


def test_env_step_batches_of_full_episodes_equal_the_fixed_trajectory_protocol():
    """Without early ends, ``env_steps = N · H`` is one round of ``N`` whole episodes: the protocol's batch."""
    horizon, trajectories = 10, 3
    results = []
    for env_steps in (None, trajectories * horizon):
        torch.manual_seed(0)
        policy = make_gaussian_policy(2, 2, hidden=(8,))
        config = AdaptationConfig(num_steps=2, num_trajectories=trajectories, horizon=horizon, env_steps=env_steps)
        env = make_eval_env("point_nav", FAR, trajectories, seed=0, horizon=horizon)
        results.append(TaskAdapter(policy, env, 2, optimizer="sgd", lr=0.1, config=config).run())
        env.close()
    torch.testing.assert_close(results[0], results[1], rtol=0, atol=0)


def test_adapter_records_the_mean_return_over_the_kept_episodes():
    horizon, trajectories, budget = 20, 4, 60
    config = AdaptationConfig(num_steps=0, num_trajectories=trajectories, horizon=horizon, env_steps=budget)
    env = make_eval_env("point_nav", torch.cat([NEAR[:1], FAR[:1]]), trajectories, seed=0, horizon=horizon)
    seen = []
    returns = TaskAdapter(_straight_policy(), env, 2, optimizer="sgd", lr=0.1, config=config).run(
        lambda k, batch: seen.append(batch.clone()))
    env.close()
    (batch,) = seen
    kept = batch["mask"].any(-1)
    assert kept.sum(-1).tolist() == [15, 3]  # the far task is padded with 12 empty trajectories
    expected = torch.stack([episode_returns(batch)[t][kept[t]].mean() for t in range(2)])
    # the near task's 4-step episodes: -(0.15 + 0.1 + 0.05 + 0)
    torch.testing.assert_close(expected[0], torch.tensor(-0.3), rtol=0, atol=1e-3)
    torch.testing.assert_close(returns[0], expected)
    torch.testing.assert_close(episode_mean(episode_returns(batch), batch), expected)


@pytest.mark.parametrize("value, error", [(0, ValueError), (-4000, ValueError), (2.5, TypeError), (True, TypeError)])
def test_bad_env_steps_is_refused_in_the_house_format(value, error):
    with pytest.raises(error, match=rf"protocol.env_steps: got {value!r}; expected an integer >= 1"):
        AdaptationConfig(env_steps=value)


def test_suite_config_accepts_env_steps_and_refuses_bad_values(tmp_path):
    cfg = compose_config("umrl/suite/config", "suite", [f"output_dir={tmp_path}", "protocol.env_steps=4000"])
    assert validate(cfg, SuiteConfig).protocol.env_steps == 4000
    assert compose_config("umrl/suite/config", "suite", [f"output_dir={tmp_path}"]).protocol.env_steps is None
    with pytest.raises(ConfigError, match=r"protocol.env_steps: got 0; expected null or an integer >= 1"):
        validate(compose_config("umrl/suite/config", "suite", [f"output_dir={tmp_path}", "protocol.env_steps=0"]),
                 SuiteConfig)


def _meta_batch(sample_by: str, horizon: int = 20, per_task: int = 4):
    """MAML's meta-training batch (:func:`umrl.trainers.maml.meta_batch`) on the near and far goals with the
    straight policy (its episodes end after 4 and 8 steps near, run to the horizon far)."""
    from types import SimpleNamespace

    from umrl.objectives.maml import MAMLLoss
    from umrl.trainers import compose
    from umrl.trainers import maml as maml_trainer
    from umrl.trainers.maml import meta_batch

    cfg = validate(compose("maml", [f"sample_by={sample_by}", f"env.horizon={horizon}",
                                    f"trajectories_per_task={per_task}", "logger.backend=none"]), MAMLConfig)
    env = make_eval_env("point_nav", torch.cat([NEAR, FAR[:1]]), per_task, seed=0, horizon=horizon)
    proposal = SimpleNamespace(env=env, num_tasks=3, trajectories_per_task=per_task, resample=lambda generator: None)
    policy = _straight_policy()
    loss = MAMLLoss(policy, inner_lr=1e-9)  # the adapted policy stays the straight one: same episode lengths
    loss.make_value_estimator(gamma=0.99, lmbda=1.0, normalize=True)
    with mock.patch.object(maml_trainer, "learning_batch", wraps=maml_trainer.learning_batch) as learning_batch:
        support, _, query, _ = meta_batch(cfg, proposal, policy, loss, torch.Generator().manual_seed(0))
    env.close()
    trajectories = [call.args[1] for call in learning_batch.call_args_list]  # collect_batch's, before packing
    for packed, batch in zip((support, query), trajectories, strict=True):
        assert (packed == pack_valid_steps(batch)).all()
    return trajectories


def test_maml_meta_training_samples_env_steps_per_task_and_early_ends_add_trajectories():
    """The MAML reference's sampler in meta-training (``sample_by=env_steps``, the default): each task's budget is
    N × H = 80 env steps, both before and after the inner step."""
    support, query = _meta_batch("env_steps")
    for batch in (support, query):
        # 4-step episodes: 20 of them; 8-step: 10; 20-step: 4 (the padded trajectories hold no step)
        assert batch["mask"].sum(-1).tolist() == [[4] * 20, [8] * 10 + [0] * 10, [20] * 4 + [0] * 16]
        assert torch.isfinite(batch["advantage"]).all()
    support, query = _meta_batch("trajectories")
    assert support["mask"].sum(-1).tolist() == [[4] * 4, [8] * 4, [20] * 4]  # the option: exactly N trajectories
    assert query.shape == support.shape == (3, 4, 20)


def test_packing_moves_each_tasks_valid_steps_in_order_into_fewer_rows():
    batch = _batch_with_lengths([[4] * 20, [8] * 10 + [0] * 10, [20] * 4 + [0] * 16], horizon=20)
    packed = pack_valid_steps(batch)
    assert packed.shape == (3, 4, 20)  # 80 valid steps per task fill 4 rows of 20 (from 20 rows)
    assert packed["mask"].all()
    for t in range(3):
        torch.testing.assert_close(packed["index"][t][packed["mask"][t]], batch["index"][t][batch["mask"][t]])
    ragged = pack_valid_steps(_batch_with_lengths([[3, 3, 3, 3], [1, 0, 0, 0]], horizon=4))
    assert ragged.shape == (2, 3, 4) and ragged["mask"].sum((-2, -1)).tolist() == [12, 1]
    full = _batch_with_lengths([[10, 10, 10], [10, 10, 10]])
    assert pack_valid_steps(full) is full  # full episodes: nothing to drop, the batch as it was
    with pytest.raises(ValueError, match=r"batch must be \[T, M, H\]"):
        pack_valid_steps(full[0])


def test_maml_loss_gradient_and_analytic_hvp_are_the_same_on_the_packed_batch():
    """The learning step computes on the packed batch (trainers.maml.learning_batch): every term is a per-task mean
    over valid steps, so the loss, its gradient, the KL Hessian-vector products and the returns it reports are the
    unpacked batch's up to float rounding, here with 20 : 10 : 4 episodes per task (a 5 x smaller batch)."""
    from umrl.objectives.maml import MAMLLoss
    from umrl.optim.meta_hvp import AnalyticHVP

    support, query = _meta_batch("env_steps")
    packed = [pack_valid_steps(b) for b in (support, query)]
    assert packed[0].shape == (3, 4, 20) and support.shape == (3, 20, 20)
    loss = MAMLLoss(make_gaussian_policy(2, 2, hidden=(8,), seed=0), inner_lr=0.1)
    vector = torch.randn(sum(p.numel() for p in loss.policy.parameters()), generator=torch.Generator().manual_seed(1))
    results = []
    for s, q in ((support, query), packed):
        out = loss(loss.pack(s, q))
        grads = torch.autograd.grad(out["loss_objective"], list(loss.policy.parameters()))
        hvp = AnalyticHVP(loss).product(s, q)
        results.append((out.detach(), torch.cat([g.reshape(-1) for g in grads]), hvp(vector)))
    (out, grad, product), (packed_out, packed_grad, packed_product) = results
    for key in ("loss_objective", "kl", "inner_loss", "return_pre", "return_post"):
        torch.testing.assert_close(packed_out[key], out[key], rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(packed_grad, grad, rtol=1e-4, atol=1e-6)
    torch.testing.assert_close(packed_product, product, rtol=1e-4, atol=1e-6)
    # the returns are means over each task's episodes, empty padded rows left out (the trainer's return_pre)
    torch.testing.assert_close(out["return_pre"], episode_mean(episode_returns(support), support).mean())
