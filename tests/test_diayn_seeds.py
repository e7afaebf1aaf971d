"""Several DIAYN seeds in one program: the fused update is SACLoss's, seeds stay independent, the reference schedule,
the per-seed replay and random streams, exact resume."""
import pytest
import torch
from script_loading import sigkill_after
from tensordict import TensorDict

from umrl.checkpoints import load_diayn_checkpoint
from umrl.checkpoints.file import read_checkpoint
from umrl.envs import make_env
from umrl.modules.discriminator import make_discriminator
from umrl.modules.sac import make_skill_actor, make_skill_qvalue
from umrl.modules.stacked_mlp import StackedMLP, linear_layers
from umrl.objectives.diayn import DIAYNLoss, DIAYNUpdate, make_diayn_optimizers
from umrl.objectives.stacked_diayn import StackedDIAYNLoss, StackedDIAYNUpdate
from umrl.seed_replay import SeedReplay
from umrl.trainers import compose
from umrl.trainers.diayn import DIAYNTrainer, train
from umrl.transforms.skill import SkillTransform

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")
K, OBS, ACT, B = 4, 3, 2, 32
LOSSES = ("loss_actor", "loss_qvalue", "loss_alpha", "loss_discriminator")


@pytest.fixture
def float64_modules():
    """Build and run the losses in float64 (TorchRL's distribution constants too), so the comparisons are tight."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(torch.float64)
    yield
    torch.set_default_dtype(previous)


def seed_loss(seed, **kwargs):
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        loss = DIAYNLoss(make_skill_actor(OBS, K, ACT, hidden=(16, 16)), make_skill_qvalue(OBS, K, ACT, hidden=(16, 16)),
                         make_discriminator(OBS, K, hidden=(16,)), num_skills=K, **kwargs)
    return loss.make_value_estimator(gamma=0.9)


def batch_of(num_seeds, dtype=torch.float64, seed=1):
    g = torch.Generator().manual_seed(seed)
    skill = torch.eye(K, dtype=dtype)[torch.randint(K, (num_seeds, B), generator=g)]
    return TensorDict({
        "observation": torch.randn(num_seeds, B, OBS, generator=g, dtype=dtype), "skill": skill,
        "action": torch.rand(num_seeds, B, ACT, generator=g, dtype=dtype) * 1.8 - 0.9,
        "next": {"observation": torch.randn(num_seeds, B, OBS, generator=g, dtype=dtype), "skill": skill,
                 "reward": torch.zeros(num_seeds, B, 1, dtype=dtype),
                 "done": torch.zeros(num_seeds, B, 1, dtype=torch.bool),
                 "terminated": torch.rand(num_seeds, B, 1, generator=g) < 0.2}}, [num_seeds, B])


def run_like_sacloss(functions, batch):
    """Call ``functions[s](batch[s])`` (a TorchRL loss or update per seed) from ``torch.manual_seed(100 + s)``, then
    give ``batch`` the standard normal noise each drew (SACLoss samples a' for the target first, then the actor's
    action); returns their outputs."""
    outputs, noise, next_noise = [], [], []
    for s, function in enumerate(functions):
        torch.manual_seed(100 + s)
        outputs.append(function(batch[s]))
        torch.manual_seed(100 + s)
        next_noise.append(torch.randn(B, ACT, dtype=torch.float64))
        noise.append(torch.randn(B, ACT, dtype=torch.float64))
    batch.set("action_noise", torch.stack(noise))
    batch.set(("next", "action_noise"), torch.stack(next_noise))
    return outputs


@pytest.mark.usefixtures("float64_modules")
@pytest.mark.parametrize("fixed_alpha", [True, False])
def test_stacked_loss_equals_torchrls_sacloss_on_the_same_batch_and_noise(fixed_alpha):
    losses = [seed_loss(s, fixed_alpha=fixed_alpha, target_entropy=-2.0) for s in range(3)]
    stacked = StackedDIAYNLoss.from_losses(losses, gamma=0.9)
    batch = batch_of(3)
    outputs = run_like_sacloss(losses, batch)
    out = stacked(batch)
    for s, reference in enumerate(outputs):
        for key in (*LOSSES, "entropy", "discriminator_accuracy", "pseudo_reward", "alpha"):
            torch.testing.assert_close(out[key][s], reference[key].detach().to(out[key].dtype), rtol=1e-12,
                                       atol=1e-12)
        sum(reference[key] for key in LOSSES).backward()
    sum(out[key].sum() for key in LOSSES).backward()
    for s, loss in enumerate(losses):  # every gradient of seed s: its own loss's
        for network, params, twins in ((stacked.actor, loss.sac_loss.actor_network_params, 1),
                                       (stacked.qvalue, loss.sac_loss.qvalue_network_params, 2)):
            rows = slice(twins * s, twins * (s + 1))
            mine = [t.grad[rows] for pair in zip(network.weights, network.biases) for t in pair]
            reference = [p.grad.reshape(twins, *p.shape[twins > 1:]) for p in params.flatten_keys().values()]
            for a, b in zip(reference, mine, strict=True):
                torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-12)


@pytest.mark.usefixtures("float64_modules")
def test_stacked_updates_follow_diayn_update_and_write_back():
    """Five fused Adam + Polyak updates of three seeds against TorchRL's SACLoss + SoftUpdate seed by seed; copy_to
    writes each seed back into a DIAYNLoss with the same parameters."""
    losses = [seed_loss(s) for s in range(3)]
    stacked = StackedDIAYNLoss.from_losses(losses, gamma=0.9)
    fused = StackedDIAYNUpdate(stacked, lr=1e-2, discriminator_lr=1e-2, tau=0.1)
    updates = [DIAYNUpdate(loss, make_diayn_optimizers(loss, lr=1e-2, discriminator_lr=1e-2), tau=0.1)
               for loss in losses]
    for step in range(5):
        batch = batch_of(3, seed=step)
        run_like_sacloss(updates, batch)
        fused(batch)
    for s, loss in enumerate(losses):
        copy = seed_loss(s)
        stacked.copy_to(s, copy)
        for (name, a), b in zip(loss.state_dict().items(), copy.state_dict().values(), strict=True):
            torch.testing.assert_close(b, a, rtol=1e-9, atol=1e-10, msg=name)


def noisy_batch(num_seeds, dtype, seed):
    """``batch_of`` with the action noise the stacked loss reads, drawn from ``seed``."""
    g = torch.Generator().manual_seed(seed + 1000)
    batch = batch_of(num_seeds, dtype=dtype, seed=seed)
    batch.set("action_noise", torch.randn(num_seeds, B, ACT, generator=g, dtype=dtype))
    return batch.set(("next", "action_noise"), torch.randn(num_seeds, B, ACT, generator=g, dtype=dtype))


@pytest.mark.parametrize("dtype, tolerance", [(torch.float64, 1e-13), (torch.float32, 2e-6)])
@pytest.mark.parametrize("fixed_alpha, num_seeds", [(True, 1), (False, 3)])
def test_hand_derived_gradients_equal_autograds(dtype, tolerance, fixed_alpha, num_seeds):
    """StackedDIAYNLoss.gradients against its forward + autograd on the same batch and noise: the same outputs (the
    losses within 1e-6; measured equal), and every gradient within ``tolerance`` of the largest element of its
    tensor (measured: 6e-16 in float64, 2.2e-7 in float32; the matmuls are grouped differently)."""
    previous = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        losses = [seed_loss(s, fixed_alpha=fixed_alpha, target_entropy=-2.0) for s in range(num_seeds)]
        reference, derived = (StackedDIAYNLoss.from_losses(losses, gamma=0.9) for _ in range(2))
    finally:
        torch.set_default_dtype(previous)
    batch = noisy_batch(num_seeds, dtype, seed=3)
    batch["next", "terminated"][0, :4] = True
    expected = reference(batch)
    sum(expected[key].sum() for key in LOSSES).backward()
    out = derived.gradients(batch)
    for key, value in expected.items():
        torch.testing.assert_close(out[key], value.detach(), rtol=0, atol=1e-6 if key in LOSSES else 0, msg=key)
    named = dict(derived.named_parameters())
    trained = {name: p for name, p in reference.named_parameters() if p.grad is not None}
    assert {name for name, p in named.items() if p.grad is not None} == set(trained)
    for name, parameter in trained.items():
        scale = parameter.grad.abs().max()
        torch.testing.assert_close(named[name].grad, parameter.grad, rtol=0, atol=tolerance * scale, msg=name)


def updates_that_agree(options: list[dict], steps: int) -> tuple[list[StackedDIAYNUpdate], list]:
    """Two :class:`StackedDIAYNUpdate` of the same three seeds (learned alpha, float32), one per ``options`` entry,
    after ``steps`` updates on the same batches, checked to agree: outputs within 1e-5, every parameter within 1e-6.
    Returns them and the seeds' initial losses."""
    losses = [seed_loss(s, fixed_alpha=False, target_entropy=-2.0).float() for s in range(3)]
    updates = [StackedDIAYNUpdate(StackedDIAYNLoss.from_losses(losses, gamma=0.9), lr=1e-3, discriminator_lr=1e-3,
                                  tau=0.1, **option) for option in options]
    for step in range(steps):
        batch = noisy_batch(3, torch.float32, seed=step)
        outs = [update(batch) for update in updates]
    torch.testing.assert_close(outs[1], outs[0], rtol=0, atol=1e-5)
    for (name, a), b in zip(updates[0].loss.state_dict().items(), updates[1].loss.state_dict().values(), strict=True):
        torch.testing.assert_close(b, a, rtol=0, atol=1e-6, msg=name)
    return updates, losses


def test_twenty_hand_derived_updates_follow_the_autograd_updates():
    """20 Adam + Polyak updates of three seeds (learned alpha) with either gradients, float32: every parameter within
    1e-6 (measured: 3e-8) after them."""
    updates, _ = updates_that_agree([{"gradients": "autograd"}, {"gradients": "analytic"}], steps=20)
    with pytest.raises(ValueError, match="gradients='numeric' is not one of"):
        StackedDIAYNUpdate(updates[0].loss, lr=1e-3, discriminator_lr=1e-3, tau=0.1, gradients="numeric")


@pytest.mark.slow
def test_compiled_hand_derived_updates_follow_the_eager_ones():
    """StackedDIAYNUpdate(compile=True) on a CPU (the hand-derived gradients under torch.compile) against eager, five
    updates of three seeds (learned alpha), float32: outputs within 1e-5 (measured: 1e-6), every parameter within
    1e-6 (measured: 3e-8). The first call compiles (≈ 1 min on 2 cores; seconds from inductor's cache)."""
    updates, losses = updates_that_agree([{"compile": False}, {"compile": True}], steps=5)
    assert not torch.equal(StackedDIAYNLoss.from_losses(losses, gamma=0.9).actor.weights[0], updates[1].loss.actor.weights[0])


@pytest.mark.parametrize("per_network_below", [0.0, 100.0])
def test_stacked_mlp_evaluates_each_network_as_its_own_linear_layers(per_network_below):
    """Batched or network by network, network n's output and gradients are those of its own layers (to float32
    rounding: a batched GEMM may round a weight gradient differently)."""
    nets = [torch.nn.Sequential(torch.nn.Linear(7, 64), torch.nn.ReLU(), torch.nn.Linear(64, 3)).float()
            for _ in range(3)]
    x = torch.randn(3, 128, 7, dtype=torch.float32)
    stacked = StackedMLP.from_linears([linear_layers(n) for n in nets])
    stacked.PER_NETWORK_BELOW = per_network_below
    assert stacked.per_network_matmuls(x) == (per_network_below > 0)
    stacked(x).square().sum().backward()
    nets[1](x[1]).square().sum().backward()
    torch.testing.assert_close(stacked(x)[1], nets[1](x[1]), rtol=0, atol=1e-6)
    for layer, weight, bias in zip(linear_layers(nets[1]), stacked.weights, stacked.biases, strict=True):
        torch.testing.assert_close(weight.grad[1], layer.weight.grad, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(bias.grad[1], layer.bias.grad, rtol=1e-5, atol=1e-5)


def tiny(output_dir, env_name, *overrides):
    return compose("diayn", [
        "logger.backend=none", "progress=false", f"output_dir={output_dir}", f"env.name={env_name}", "num_skills=3",
        "env.horizon=10", "collector.total_frames=120", "collector.init_random_frames=40", "network.hidden=[16,16]",
        "network.discriminator_hidden=[16]", "replay_buffer.batch_size=16", "replay_buffer.size=1000",
        "eval.every=80", "eval.episodes_per_skill=2", "checkpoint.every=80", *overrides])


DEFAULT_SIZES = ("network.hidden=[300,300]", "network.discriminator_hidden=[300,300]", "replay_buffer.batch_size=128",
                 "collector.init_random_frames=128", "collector.total_frames=150", "eval.every=150",
                 "checkpoint.every=150")


SEED_ROUNDING = 1e-6
"""The most a seed's parameters may differ between a run alone and among others after these tests' 23-82 updates
(measured: at most 3.0e-8 in all three; batched and single GEMMs and the fused Adam round some elements
differently)."""


@pytest.mark.parametrize(("env_name", "sizes"), [("point_nav", ()), ("half_cheetah", ("env.num_envs=2",)),
                                                 ("half_cheetah", DEFAULT_SIZES)])
def test_a_seed_alone_and_among_others_trains_the_same_networks(tmp_path, env_name, sizes):
    """Seed 1 alone and seed 1 inside seeds=[0,1,2]: the same data, the same updates, the same networks to float
    rounding (tiny networks, with two env copies per seed, and the recipe's 2x300 networks at batch 128)."""
    train(tiny(tmp_path / "three", env_name, "seeds=[0,1,2]", *sizes))
    train(tiny(tmp_path / "alone", env_name, "seed=1", *sizes))
    together, alone = load_diayn_checkpoint(tmp_path / "three" / "seed1"), load_diayn_checkpoint(tmp_path / "alone")
    assert together["counters"]["updates"] == alone["counters"]["updates"] > 0
    for part in ("actor", "discriminator"):
        assert together[part].keys() == alone[part].keys()
        worst = max((together[part][k] - alone[part][k]).abs().max().item() for k in alone[part])
        assert worst <= SEED_ROUNDING, (part, worst)
    other = load_diayn_checkpoint(tmp_path / "three" / "seed0")  # and the seeds did train apart
    assert max((other["actor"][k] - alone["actor"][k]).abs().max().item() for k in alone["actor"]) > 1e-3


def test_the_recipe_passes_its_compile_setting_to_the_update(tmp_path):
    """optim.compile=true on a CPU compiles the update's hand-derived gradients (compiled at the first update, which
    this test does not reach); false keeps them eager."""
    for compile in (False, True):
        trainer = DIAYNTrainer(tiny(tmp_path / str(compile), "point_nav", f"optim.compile={compile}"))
        assert (trainer.update.runner.compiled_target is not None) == compile
        trainer.close()


def test_two_seeds_resume_bit_identically(tmp_path):
    whole = train(tiny(tmp_path / "whole", "half_cheetah", "seeds=[3,5]"))
    train(tiny(tmp_path / "split", "half_cheetah", "seeds=[3,5]", "collector.total_frames=80"))
    resumed = train(tiny(tmp_path / "split", "half_cheetah", "seeds=[3,5]", "resume=true"))
    a, b = read_checkpoint(whole["checkpoint"]), read_checkpoint(resumed["checkpoint"])
    assert a["counters"] == b["counters"] and a["counters"]["frames"] == 120
    for key in a["loss"]:
        assert torch.equal(a["loss"][key], b["loss"][key]), key
    assert torch.equal(a["replay"]["rows"]["observation"], b["replay"]["rows"]["observation"])
    assert torch.equal(a["rng"]["generators"]["seed5"], b["rng"]["generators"]["seed5"])


def test_the_default_schedule_is_one_env_step_then_one_update(tmp_path):
    """After the warm-up, every step takes one env step per seed and one update; frames_per_batch of a whole episode
    per copy is the bulk schedule, with as many updates at once."""
    trainer = DIAYNTrainer(tiny(tmp_path / "interleaved", "point_nav", "seeds=[0,1]"))
    counts = []
    for _ in range(45):
        trainer.step()
        counts.append((trainer.counters["frames"], trainer.counters["updates"]))
    trainer.close()
    assert counts[38] == (39, 0) and counts[39] == (40, 1)  # updates start when the replay holds the warm-up
    assert all(u == f - 39 for f, u in counts[39:])
    bulk = DIAYNTrainer(tiny(tmp_path / "bulk", "point_nav", "env.num_envs=4", "collector.frames_per_batch=40"))
    bulk.step()
    assert (bulk.counters["frames"], bulk.counters["updates"]) == (40, 40)
    bulk.close()


def test_seed_replay_keeps_seeds_apart_and_round_trips_through_its_state():
    gens = [torch.Generator().manual_seed(s) for s in (0, 1)]
    replay = SeedReplay(5, batch_size=64, generators=gens, act_dim=1)
    rows = torch.arange(14.0).view(7, 2, 1)  # seed 0 even, seed 1 odd; 7 rows into 5: the first two overwritten
    replay.extend(TensorDict({"observation": rows[:4]}, [4, 2]))
    replay.extend(TensorDict({"observation": rows[4:]}, [3, 2]))
    assert len(replay) == 5
    sample = replay.sample()["observation"]
    assert set(sample[0].view(-1).tolist()) <= {4.0, 6.0, 8.0, 10.0, 12.0} and (sample[1] % 2 == 1).all()
    copy = SeedReplay(5, batch_size=64, generators=[torch.Generator().manual_seed(s) for s in (0, 1)], act_dim=1)
    copy.load_state_dict(replay.state_dict())
    assert torch.equal(copy.storage["observation"], replay.storage["observation"]) and copy.cursor == replay.cursor
    with pytest.raises(ValueError, match=r"expected transitions \[N, 2\]"):
        replay.extend(TensorDict({"observation": rows[:, :1]}, [7, 1]))


def test_each_seeds_copies_reset_from_their_own_streams():
    """A group of MuJoCo copies resets with the noise of an env seeded alone with its seed; skills are drawn from the
    group's generator, only where a copy resets."""
    env = make_env("half_cheetah", 4, seed=0, horizon=3)
    env.base_env.seed_copies([7, 9])
    gens = [torch.Generator().manual_seed(7), torch.Generator().manual_seed(9)]
    env.append_transform(SkillTransform(5, generators=gens))
    first = env.reset()
    alone = make_env("half_cheetah", 2, seed=9, horizon=3).reset()
    torch.testing.assert_close(first["observation"][2:], alone["observation"], rtol=0, atol=0)
    expected = torch.randint(5, (2,), generator=torch.Generator().manual_seed(9))
    assert torch.equal(first["skill"][2:].argmax(-1), expected)
    state = gens[0].get_state()
    partial = first.clone().set("_reset", torch.tensor([False, False, True, False]).unsqueeze(-1))
    env.reset(partial)
    assert torch.equal(gens[0].get_state(), state)  # seed 7's copies did not reset: its stream did not move
    with pytest.raises(ValueError, match="equal groups"):
        env.base_env.seed_copies([1, 2, 3])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
@pytest.mark.parametrize("cudagraphs", [False, True])
def test_stacked_update_trains_on_cuda(cudagraphs):
    losses = [seed_loss(s).float() for s in range(2)]
    stacked = StackedDIAYNLoss.from_losses(losses, gamma=0.9).to("cuda")
    update = StackedDIAYNUpdate(stacked, lr=1e-3, discriminator_lr=1e-3, tau=0.01, cudagraphs=cudagraphs)
    before = [p.detach().clone() for p in stacked.actor.parameters()]
    for step in range(8):  # CUDA graphs capture after their warm-up calls
        batch = batch_of(2, dtype=torch.float32, seed=step).to("cuda")
        batch.set("action_noise", torch.randn(2, B, ACT, device="cuda"))
        batch.set(("next", "action_noise"), torch.randn(2, B, ACT, device="cuda"))
        out = update(batch)
    assert torch.isfinite(out["loss_qvalue"]).all()
    assert any(not torch.equal(a, b) for a, b in zip(before, stacked.actor.parameters()))


def test_cudagraphs_off_a_gpu_is_refused():
    stacked = StackedDIAYNLoss.from_losses([seed_loss(0).float()], gamma=0.9)
    with pytest.raises(ValueError, match="cudagraphs=True needs the loss on a CUDA device"):
        StackedDIAYNUpdate(stacked, lr=1e-3, discriminator_lr=1e-3, tau=0.01, cudagraphs=True)


def test_a_killed_run_of_two_seeds_resumes_to_the_uninterrupted_numbers(tmp_path):
    """recipes/diayn.py with seeds=[0,1] killed with SIGKILL after its second checkpoint, resumed in-process: the
    same final program checkpoint, tensor for tensor, as an uninterrupted run."""
    overrides = ["env.name=half_cheetah", "seeds=[0,1]", "collector.total_frames=600", "checkpoint.every=40",
                 "eval.every=600"]
    killed = tmp_path / "killed"
    command = ["recipes/diayn.py", "logger.backend=none", "progress=false", f"output_dir={killed}", "num_skills=3", "env.horizon=10",
                "collector.init_random_frames=40", "network.hidden=[16,16]", "network.discriminator_hidden=[16]",
                "replay_buffer.batch_size=16", "replay_buffer.size=1000", "eval.episodes_per_skill=2", *overrides]
    sigkill_after(command, killed / "checkpoints" / "step_80.safetensors")
    resumed = train(tiny(killed, "half_cheetah", *overrides, "resume=true"))
    whole = train(tiny(tmp_path / "whole", "half_cheetah", *overrides))
    a, b = read_checkpoint(whole["checkpoint"]), read_checkpoint(resumed["checkpoint"])
    assert a["counters"] == b["counters"] and a["counters"]["frames"] == 600
    assert all(torch.equal(a["loss"][key], b["loss"][key]) for key in a["loss"])
