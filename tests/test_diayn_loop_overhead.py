"""DIAYN's training loop with less per-step overhead, the same numbers: the replay's sample by one gather per key, the
stacked update's one compile path."""
import pytest
import torch
from tensordict import TensorDict
from test_diayn_seeds import noisy_batch, seed_loss

from umrl.objectives.stacked_diayn import StackedDIAYNLoss, StackedDIAYNUpdate
from umrl.seed_replay import SeedReplay


def test_the_replay_sample_is_seed_columns_at_each_seeds_own_rows():
    """Seed s's sample: rows drawn by its generator, from column s only (a wrapped ring), then its action noise."""
    gens = [torch.Generator().manual_seed(s) for s in (0, 1, 2)]
    replay = SeedReplay(7, batch_size=5, generators=gens, act_dim=2)
    rows = torch.arange(10.0).view(10, 1, 1).expand(10, 3, 1) * 10 + torch.arange(3.0).view(1, 3, 1)
    for lo, hi in ((0, 6), (6, 10)):  # the second write wraps around the ring
        replay.extend(TensorDict({"observation": rows[lo:hi], "next": {"observation": -rows[lo:hi]}}, [hi - lo, 3]))
    copies = [torch.Generator().manual_seed(s) for s in (0, 1, 2)]
    for g, c in zip(gens, copies):
        c.set_state(g.get_state())
    batch = replay.sample()
    assert batch.batch_size == torch.Size([3, 5]) and batch.device == torch.device("cpu")
    for s, g in enumerate(copies):
        index = torch.randint(7, (5,), generator=g)
        assert torch.equal(batch["observation"][s], replay.storage["observation"][index, s])
        assert torch.equal(batch["next", "observation"][s], -batch["observation"][s])
    for key in (("next", "action_noise"), "action_noise"):
        assert torch.equal(batch[key], torch.stack([torch.randn(5, 2, generator=g) for g in copies]))


def stacked_update(**options):
    losses = [seed_loss(s, fixed_alpha=False, target_entropy=-2.0).float() for s in range(2)]
    return StackedDIAYNUpdate(StackedDIAYNLoss.from_losses(losses, gamma=0.9), lr=1e-3, discriminator_lr=1e-3,
                              tau=0.1, **options)


def test_the_stacked_updates_cpu_compile_path_checks_and_reports_as_the_runner(monkeypatch):
    """On a CPU ``compile`` compiles the hand-derived gradients alone, through UpdateRunner: the same mode check, and a
    compiler failure re-raised naming the option that turns it off."""
    with pytest.raises(ValueError, match="compile mode 'fast'.*reduce-overhead"):
        stacked_update(compile="fast")
    compiled = []

    def unsupported(fn, **kwargs):
        compiled.append((fn.__name__, kwargs["mode"]))

        def run(*args):
            raise torch._dynamo.exc.TorchDynamoException("unsupported op")
        return run

    monkeypatch.setattr(torch, "compile", unsupported)
    update = stacked_update(compile=True)
    assert compiled == [("hand_derived_gradients", "default")]
    with pytest.raises(RuntimeError, match=r"(?s)compile='default'.*unsupported op.*compile=False"):
        update(noisy_batch(2, torch.float32, seed=0))
    assert stacked_update(gradients="autograd").runner.compiled_target is None
