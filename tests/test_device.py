"""One ``device`` setting honoured end to end: every tensor a recipe or a meta-test cell creates lives on it.

Each recipe runs on a tiny budget while the test captures what it builds (networks, loss, optimiser state, replay
storage, collected batches, env outputs) and asserts ``tensor.device == torch.device(device)`` for every tensor it
can reach. The same tests run on CUDA where a GPU exists (skipped cleanly otherwise). A checkpoint stores its tensors
as CPU data, so one written on a GPU loads on this machine; ``device=cuda`` without a GPU fails at the start, naming the device and the choices.
"""
import pytest
import torch
from tensordict import TensorDictBase

import umrl.trainers.diayn
import umrl.trainers.maml
import umrl.trainers.vime
from umrl.checkpoints import load_maml_policy
from umrl.envs import make_env, make_task_env
from umrl.metatest import methods as metatest_methods
from umrl.metatest.methods import CellSpec, run_cell
from umrl.metatest.protocol import AdaptationConfig, TaskAdapter, make_eval_env, select_skills
from umrl.modules.policy import make_gaussian_policy
from umrl.modules.sac import make_skill_actor
from umrl.proposals import make_proposal
from umrl.rollout import collect
from umrl.trainers import compose

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
DEVICES = ["cpu", pytest.param("cuda", marks=CUDA)]


def tensors(obj, name="obj"):
    """Every tensor reachable from ``obj`` as ``(name, tensor)``: modules (parameters and buffers), TensorDicts,
    optimisers (state), replay buffers (storage), and containers of these."""
    if isinstance(obj, torch.Tensor):
        yield name, obj
    elif isinstance(obj, TensorDictBase):
        for key, value in obj.items(True, True):
            yield f"{name}[{key}]", value
    elif isinstance(obj, torch.nn.Module):
        yield from ((f"{name}.{k}", v) for k, v in obj.state_dict(keep_vars=True).items())
    elif isinstance(obj, torch.optim.Optimizer):
        # torch keeps the step count of a non-capturable, non-fused Adam on the host by design (no sync per step)
        host_step = not any(group.get("capturable") or group.get("fused") for group in obj.param_groups)
        for i, state in enumerate(obj.state.values()):
            state = {k: v for k, v in state.items() if not (host_step and k == "step" and v.ndim == 0)}
            yield from tensors(state, f"{name}.state[{i}]")
    elif hasattr(obj, "storage") and hasattr(obj, "sample"):  # a TorchRL replay buffer
        yield from tensors(obj[:], f"{name}.storage")
    elif isinstance(obj, dict):
        for key, value in obj.items():
            yield from tensors(value, f"{name}[{key!r}]")
    elif isinstance(obj, (list, tuple)):
        for i, value in enumerate(obj):
            yield from tensors(value, f"{name}[{i}]")


def assert_on(device, **objects):
    """Every tensor reachable from ``objects`` lives on ``device`` (and there is at least one)."""
    device = torch.device(device)
    found = [(name, t) for key, obj in objects.items() for name, t in tensors(obj, key)]
    assert found, f"no tensor reachable from {list(objects)}"
    wrong = {name: str(t.device) for name, t in found if t.device.type != device.type}
    assert not wrong, f"tensors not on {device}: {wrong}"


def capture(monkeypatch, module, name, store):
    """Replace ``module.name`` by a wrapper that records its arguments and results in ``store[name]``."""
    original = getattr(module, name)

    def wrapper(*args, **kwargs):
        store.setdefault(name, []).append([args, kwargs, None])
        store[name][-1][2] = result = original(*args, **kwargs)
        return result

    monkeypatch.setattr(module, name, wrapper)


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("env_name", ["point_nav", "half_cheetah"])
def test_env_outputs_live_on_the_device(device, env_name):
    env = make_task_env(env_name, torch.zeros(3, 2 if env_name == "point_nav" else 1), device=device, horizon=4)
    assert env.device.type == torch.device(device).type
    assert_on(device, rollout=env.rollout(4), transforms=env.transform)
    env.close()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name", ["oracle", "random"])
def test_proposal_env_discriminator_and_batches_on_the_device(device, name):
    proposal = make_proposal(name, "point_nav", num_tasks=2, trajectories_per_task=3, horizon=5, num_skills=4,
                             discriminator_hidden=[8], device=device)
    proposal.resample(torch.Generator().manual_seed(0))
    policy = make_gaussian_policy(2, 2, hidden=[8]).to(device)
    batch = collect(proposal.env, policy, num_tasks=2, horizon=5)
    assert_on(device, batch=batch, transforms=proposal.env.transform)


@pytest.mark.parametrize("device", DEVICES)
def test_maml_recipe_keeps_everything_on_the_device(tmp_path, device, monkeypatch):
    seen = {}
    capture(monkeypatch, umrl.trainers.maml, "build", seen)
    capture(monkeypatch, umrl.trainers.maml, "collect_env_steps", seen)  # the default sampler (sample_by=env_steps)
    cfg = compose("maml", [f"device={device}", "env.horizon=5", "meta_batch_size=2", "trajectories_per_task=2",
                           "policy.hidden=[8]", "logger.backend=none", "progress=false", "trpo.cg_iters=2",
                           "iterations=1", f"output_dir={tmp_path}"])
    umrl.trainers.maml.train(cfg)
    proposal, policy, loss, trpo = seen["build"][0][2]
    assert_on(device, policy=policy, loss=loss, trpo=vars(trpo), env=proposal.env.transform,
              batches=[result for _, _, result in seen["collect_env_steps"]])


@pytest.mark.parametrize("device", DEVICES)
def test_diayn_recipe_keeps_everything_on_the_device(tmp_path, device, monkeypatch):
    seen = {}
    capture(monkeypatch, umrl.trainers.diayn, "save_diayn_checkpoint", seen)
    capture(monkeypatch, umrl.trainers.diayn, "StackedDIAYNUpdate", seen)
    capture(monkeypatch, umrl.trainers.diayn, "SeedReplay", seen)
    capture(monkeypatch, umrl.trainers.diayn, "evaluate_skills", seen)
    cfg = compose("diayn", [
        f"device={device}", "logger.backend=none", "progress=false", f"output_dir={tmp_path}", "num_skills=3",
        "env.num_envs=4", "env.horizon=5", "collector.frames_per_batch=20", "collector.total_frames=40",
        "collector.init_random_frames=20", "optim.updates_per_frame=0.1", "network.hidden=[8]",
        "network.discriminator_hidden=[8]", "replay_buffer.batch_size=8", "eval.every=40",
        "eval.episodes_per_skill=1", "checkpoint.every=40"])
    umrl.trainers.diayn.train(cfg)
    saved = seen["save_diayn_checkpoint"][-1][1]
    update = seen["StackedDIAYNUpdate"][0][2]
    assert all(opt.state for opt in update.optimizers.values()), "the optimisers took no step"
    replay = seen["SeedReplay"][0][2]
    assert len(replay) == 40
    assert_on(device, actor=saved["actor"], discriminator=saved["discriminator"], loss=update.loss,
              optimizers={name: opt.state_dict() for name, opt in update.optimizers.items()},
              buffer=replay.storage[:len(replay)], sample=replay.sample(),
              evaluations=[result for _, _, result in seen["evaluate_skills"]])


@pytest.mark.parametrize("device", DEVICES)
def test_vime_recipe_keeps_everything_on_the_device(tmp_path, device, monkeypatch):
    seen = {}
    capture(monkeypatch, umrl.trainers.vime, "save_vime_checkpoint", seen)
    capture(monkeypatch, umrl.trainers.vime, "collect", seen)
    cfg = compose("vime", [
        f"device={device}", "logger.backend=none", "progress=false", f"output_dir={tmp_path}", "iterations=1",
        "env.num_envs=4", "env.horizon=5", "policy.hidden=[8]", "dynamics.updates_per_iteration=2",
        "dynamics.batch_size=4", "dynamics.holdout_fraction=0.25", "checkpoint.every=1"])
    umrl.trainers.vime.train(cfg)
    saved = seen["save_vime_checkpoint"][-1][1]
    assert saved["dynamics_optimizer"].state, "the dynamics model took no step"
    assert_on(device, **{k: saved[k] for k in ("policy", "dynamics", "dynamics_optimizer", "median_history",
                                              "replay", "holdout", "visited")},
              batches=[result for _, _, result in seen["collect"]])


@pytest.mark.parametrize("device", DEVICES)
def test_task_adapter_params_optimizer_and_batches_on_the_device(device):
    config = AdaptationConfig(num_steps=1, num_trajectories=2, horizon=5)
    env = make_eval_env("point_nav", torch.zeros(3, 2), 2, seed=0, horizon=5, device=device)
    policy = make_gaussian_policy(2, 2, hidden=[8]).to(device)
    adapter = TaskAdapter(policy, env, 3, optimizer="adam", lr=1e-2, config=config)
    batch = adapter.collect()
    adapter.step(batch)
    assert_on(device, params=adapter.params, optimizer=adapter.optimizer, batch=batch)
    actor = make_skill_actor(2, 4, 2, hidden=[8]).to(device)
    best, returns = select_skills(actor, "point_nav", torch.zeros(2, 2), 4, num_trajectories=2, seed=0, horizon=5,
                                  device=device)
    assert_on(device, best=best, returns=returns)


@pytest.mark.parametrize("device", DEVICES)
def test_metatest_cell_runs_on_the_device(tmp_path, device, monkeypatch):
    seen = {}
    capture(monkeypatch, metatest_methods, "TaskAdapter", seen)
    spec = CellSpec(method="scratch", env="point_nav", seed=0, output=str(tmp_path / "cell.csv"), num_tasks=2,
                    protocol=AdaptationConfig(num_steps=1, num_trajectories=2, horizon=5), device=device)
    assert (tmp_path / "cell.csv").samefile(run_cell(spec))
    adapter = seen["TaskAdapter"][0][2]
    assert_on(device, policy=adapter.policy, params=adapter.params, optimizer=adapter.optimizer)


def test_a_checkpoint_written_on_a_gpu_loads_on_the_cpu(tmp_path):
    """The checkpoint file stores every tensor as CPU data: what a GPU run saves loads on this machine."""
    from umrl.checkpoints.file import encode

    if torch.cuda.is_available():
        _, tensors = encode({"w": torch.ones(2, device="cuda")})
        assert tensors["t0"].device.type == "cpu"
    cfg = compose("maml", ["env.horizon=5", "meta_batch_size=2", "trajectories_per_task=2", "policy.hidden=[8]",
                           "logger.backend=none", "progress=false", "iterations=1", "trpo.cg_iters=2",
                           f"output_dir={tmp_path}"])
    umrl.trainers.maml.train(cfg)
    policy, _ = load_maml_policy(tmp_path)
    assert_on("cpu", policy=policy)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error on a machine without a GPU")
def test_cuda_without_a_gpu_fails_at_the_start(tmp_path):
    for name, extra in (("maml", ["iterations=1"]), ("diayn", []), ("vime", [])):
        cfg = compose(name, ["device=cuda", "logger.backend=none", "progress=false", f"output_dir={tmp_path / name}",
                             *extra])
        with pytest.raises(ValueError, match=r"device.*'cuda'.*'cpu', 'auto'"):
            getattr(umrl.trainers, name).train(cfg)
        assert not (tmp_path / name / "checkpoints").exists()
    spec = CellSpec(method="scratch", env="point_nav", seed=0, output=str(tmp_path / "cell.csv"), device="cuda")
    with pytest.raises(ValueError, match=r"device.*'cuda'.*'cpu', 'auto'"):
        run_cell(spec)
    with pytest.raises(ValueError, match=r"device.*'gpu'.*'cpu', 'cuda', 'auto'"):
        CellSpec(method="scratch", env="point_nav", seed=0, output=str(tmp_path / "cell.csv"), device="gpu")


def test_make_env_defaults_to_cpu():
    assert make_env("point_nav", 2).device == torch.device("cpu")


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("hvp_fraction", [1.0, 0.5])
def test_meta_step_from_one_batch_is_the_cpus_on_every_device(device, hvp_fraction):
    """The MAML recipe's TRPO meta-step from the same parameters, batch and subsample generator takes the CPU's step
    on ``device``: the same line-search trials, parameters equal to float rounding (bit for bit on the CPU). A GPU
    run's numbers may differ from a CPU run's only through its own random draws, not through the update.

    The damping is 1, not the recipe's 1e-5: this batch's KL Hessian (320 steps, ~1,300 parameters) is
    rank-deficient, and at 1e-5 conjugate gradient amplifies rounding so much that parameters nudged by one ulp move
    the CPU's own step by 3-16 % of its norm, 500-1,200 times this test's tolerance. At 1 the same nudge moves it by
    ~5e-6 of its norm (docs/measurements/2026-11-26-cpu/meta_step_rounding_sensitivity.log)."""
    overrides = ["env.horizon=20", "meta_batch_size=4", "trajectories_per_task=4", "policy.hidden=[32, 32]",
                 f"trpo.hvp_fraction={hvp_fraction}", "trpo.damping=1.0", "logger.backend=none", "progress=false"]
    cfg = compose("maml", ["device=cpu", *overrides])
    proposal, policy, loss, trpo = umrl.trainers.maml.build(cfg, torch.Generator().manual_seed(1))
    initial = {k: v.clone() for k, v in policy.state_dict().items()}
    support, adapted, query, _ = umrl.trainers.maml.meta_batch(cfg, proposal, policy, loss, torch.Generator().manual_seed(0))
    reference = umrl.trainers.maml.meta_step(cfg, loss, trpo, support, query, adapted)

    cfg = compose("maml", [f"device={device}", *overrides])
    _, other_policy, other_loss, other_trpo = umrl.trainers.maml.build(cfg, torch.Generator().manual_seed(1))
    other_policy.load_state_dict(initial)
    support, query = support.to(device), query.to(device)
    with torch.enable_grad():
        other_adapted = other_loss.adapt(support)
    info = umrl.trainers.maml.meta_step(cfg, other_loss, other_trpo, support, query, other_adapted)

    assert reference["accepted"] == 1.0
    assert (info["accepted"], info["backtracks"]) == (reference["accepted"], reference["backtracks"])
    stepped = policy.state_dict()
    assert any(not torch.equal(stepped[k], initial[k]) for k in initial)
    for key, value in other_policy.state_dict().items():
        if device == "cpu":
            assert torch.equal(value, stepped[key]), key
        else:
            torch.testing.assert_close(value.cpu(), stepped[key], rtol=1e-4, atol=1e-5,
                                       msg=lambda message, key=key: f"{key}: {message}")
