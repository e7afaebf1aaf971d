"""DIAYNUpdate: the one SAC + discriminator update (eager, compiled, CUDA graphs) against the plain loop."""
import pytest
import torch
from tensordict import TensorDict
from torchrl.objectives import SoftUpdate

from umrl.modules.discriminator import make_discriminator
from umrl.modules.sac import make_skill_actor, make_skill_qvalue
from umrl.objectives.diayn import DIAYNLoss, DIAYNUpdate, _distribution_kwargs_to, make_diayn_optimizers

OBS, ACT, K, B = 3, 2, 4, 32
cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def make_loss(device="cpu", fixed_alpha=True):
    torch.manual_seed(0)
    loss = DIAYNLoss(make_skill_actor(OBS, K, ACT, hidden=(16,)), make_skill_qvalue(OBS, K, ACT, hidden=(16,)),
                     make_discriminator(OBS, K, hidden=(16,)), num_skills=K, fixed_alpha=fixed_alpha,
                     target_entropy=-float(ACT))
    return loss.make_value_estimator(gamma=0.99).to(device)


def make_batches(n, device="cpu"):
    """Separable skills: skill k's observations (s_t, which D scores) and next observations sit around 3 * e_k
    (mod OBS, signed), so D can learn them."""
    g = torch.Generator().manual_seed(1)
    batches = []
    for _ in range(n):
        label = torch.randint(K, (B,), generator=g)
        z = torch.eye(K)[label]
        centre = 3.0 * torch.eye(OBS)[label % OBS] * torch.where(label < OBS, 1.0, -1.0)[:, None]
        batches.append(TensorDict({
            "observation": centre + 0.1 * torch.randn(B, OBS, generator=g), "skill": z,
            "action": torch.rand(B, ACT, generator=g) * 2 - 1,
            "next": {"observation": centre + 0.1 * torch.randn(B, OBS, generator=g), "skill": z,
                     "reward": torch.zeros(B, 1), "done": torch.zeros(B, 1, dtype=torch.bool),
                     "terminated": torch.zeros(B, 1, dtype=torch.bool)},
        }, [B]).to(device))
    return batches


def plain_loop(loss, optimizers, batches, tau):
    """The reference: the recipe's loop written out by hand."""
    target_updater = SoftUpdate(loss.sac_loss, tau=tau)
    for batch in batches:
        out = loss(batch)
        for optimizer in optimizers.values():
            optimizer.zero_grad(set_to_none=True)
        sum(v for k, v in out.items() if k.startswith("loss_")).backward()
        for optimizer in optimizers.values():
            optimizer.step()
        target_updater.step()


@pytest.mark.parametrize("fixed_alpha", [True, False])
def test_update_matches_the_plain_loop_on_cpu(fixed_alpha):
    batches = make_batches(4)
    reference, loss = make_loss(fixed_alpha=fixed_alpha), make_loss(fixed_alpha=fixed_alpha)
    before = TensorDict.from_module(loss).clone()
    torch.manual_seed(5)
    plain_loop(reference, make_diayn_optimizers(reference, lr=1e-2, discriminator_lr=1e-2), batches, tau=0.1)
    update = DIAYNUpdate(loss, make_diayn_optimizers(loss, lr=1e-2, discriminator_lr=1e-2), tau=0.1)
    assert set(update.optimizers) == {"actor", "qvalue", "discriminator"} | (set() if fixed_alpha else {"alpha"})
    torch.manual_seed(5)
    for batch in batches:
        out = update(batch)
    assert not any(v.requires_grad for v in out.values(True, True))
    after, expected = TensorDict.from_module(loss), TensorDict.from_module(reference)
    for key, value in after.items(True, True):
        torch.testing.assert_close(value, expected[key], msg=f"{key} differs from the plain loop")
    trained = [k for k, v in after.items(True, True) if isinstance(v, torch.nn.Parameter) and v.requires_grad]
    targets = [k for k in after.keys(True, True) if k[:2] == ("sac_loss", "target_qvalue_network_params")]
    assert targets and len(trained) >= 3 * 2 + 2 * int(not fixed_alpha)
    for key in trained + targets:  # every trained parameter and every target net moved
        assert not torch.equal(after[key], before[key]), f"{key} did not change"
    assert all(p.grad is None for p in loss.parameters())  # gradients are cleared after every update


def test_bad_options():
    loss = make_loss()
    with pytest.raises(ValueError, match="cudagraphs=True needs the loss on a CUDA device.*cpu"):
        DIAYNUpdate(loss, make_diayn_optimizers(loss, lr=1e-3, discriminator_lr=1e-3), tau=0.01, cudagraphs=True)
    with pytest.raises(ValueError, match="compile mode 'fast'.*reduce-overhead"):
        DIAYNUpdate(loss, make_diayn_optimizers(loss, lr=1e-3, discriminator_lr=1e-3), tau=0.01, compile="fast")


def test_compile_failure_names_the_option_and_the_way_out(monkeypatch):
    """torch.compile compiles lazily (second call); a Dynamo failure there is re-raised saying how to turn it off."""

    def unsupported(fn, **kwargs):
        def run(*args):
            raise torch._dynamo.exc.TorchDynamoException("unsupported op")
        return run

    monkeypatch.setattr(torch, "compile", unsupported)
    loss = make_loss()
    update = DIAYNUpdate(loss, make_diayn_optimizers(loss, lr=1e-3, discriminator_lr=1e-3), tau=0.01, compile=True)
    batch = make_batches(1)[0]
    update(batch)  # the eager warm-up call
    with pytest.raises(RuntimeError, match=r"(?s)compile='reduce-overhead'.*unsupported op.*compile=False"):
        update(batch)


def test_distribution_bounds_become_tensors_with_the_same_samples():
    """What cudagraphs=True does to the actor (capture cannot copy host numbers): same draws, to the bit."""
    loss = make_loss()
    actor = loss.sac_loss.actor_network
    td = make_batches(1)[0].select("observation", "skill")
    torch.manual_seed(3)
    before = actor(td.clone())
    _distribution_kwargs_to(actor, torch.device("cpu"))
    kwargs = [m.distribution_kwargs for m in actor.modules() if getattr(m, "distribution_kwargs", None)]
    assert kwargs and all(isinstance(k["low"], torch.Tensor) and isinstance(k["high"], torch.Tensor) for k in kwargs)
    torch.manual_seed(3)
    after = actor(td.clone())
    assert torch.equal(before["action"], after["action"])
    assert torch.equal(before["action_log_prob"], after["action_log_prob"])


@pytest.mark.parametrize("device, cudagraphs", [("cpu", False), pytest.param("cuda", False, marks=cuda),
                                                pytest.param("cuda", True, marks=cuda)])
def test_update_trains(device, cudagraphs):
    """D learns separable skills in 61 updates on every device (the CPU run keeps the check from going stale)."""
    loss = make_loss(device)
    update = DIAYNUpdate(loss, make_diayn_optimizers(loss, lr=1e-2, discriminator_lr=1e-2, capturable=cudagraphs),
                         tau=0.01, cudagraphs=cudagraphs)
    batches = make_batches(8, device)
    first = update(batches[0])
    for i in range(60):
        out = update(batches[i % len(batches)])
    assert all(v.device.type == device for v in TensorDict.from_module(loss).values(True, True))
    assert out["loss_discriminator"].device.type == device
    assert torch.isfinite(torch.stack([v for k, v in out.items() if k.startswith("loss_")])).all()
    assert out["loss_discriminator"] < 0.5 * first["loss_discriminator"]
    assert out["discriminator_accuracy"] > 0.9


@cuda
def test_cudagraphs_need_capturable_optimizers():
    loss = make_loss("cuda")
    with pytest.raises(ValueError, match="capturable"):
        DIAYNUpdate(loss, make_diayn_optimizers(loss, lr=1e-3, discriminator_lr=1e-3), tau=0.01, cudagraphs=True)
