"""Every loss honours TorchRL's contract: forward(td), set_keys, in_keys / out_keys (per instance, select_out_keys),
repr, make_value_estimator, target updaters built on the loss itself."""
import copy
import warnings

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import RenameTransform
from torchrl.modules import MLP, ValueOperator
from torchrl.objectives import SoftUpdate
from torchrl.objectives.utils import ValueEstimators
from torchrl.objectives.value import TD0Estimator

from umrl.modules.bnn import BayesianDynamics
from umrl.modules.discriminator import make_discriminator
from umrl.modules.policy import make_gaussian_policy
from umrl.modules.sac import make_skill_actor, make_skill_qvalue
from umrl.objectives import DIAYNLoss, ImportanceSamplingLoss, MAMLLoss, VIMELoss
from umrl.objectives.stacked_diayn import StackedDIAYNLoss
from umrl.optim import META_HVPS, KLHessian, TRPOStep, make_meta_hvp
from umrl.proposals import make_proposal
from umrl.rollout import collect

T, N, H, OBS, ACT, K = 2, 3, 4, 2, 2, 4


def _trajectories(policy, *, seed, shape=(T, N, H)):
    g = torch.Generator().manual_seed(seed)
    td = TensorDict({"observation": torch.randn(*shape, OBS, generator=g),
                     "step_count": torch.arange(H).expand(*shape).unsqueeze(-1),
                     "next": {"reward": torch.randn(*shape, 1, generator=g),
                              "done": torch.zeros(*shape, 1, dtype=torch.bool)}}, list(shape))
    with torch.no_grad():
        return policy(td)


def _maml():
    torch.manual_seed(0)
    policy = make_gaussian_policy(OBS, ACT, hidden=(8,))
    loss = MAMLLoss(policy, inner_lr=0.5).make_value_estimator(gamma=0.9)
    support = loss.value_estimator(_trajectories(policy, seed=1))
    with torch.no_grad():
        adapted = loss.adapt(support)
    query = _trajectories(policy, seed=2)
    with torch.no_grad():  # the query as the adapted policy collected it
        query.update(loss.functional_policy.act(adapted, query).exclude("action"))
        query["action_log_prob"] = loss.functional_policy.log_prob(adapted, query)
    return loss, support, loss.value_estimator(query)


def _diayn():
    return DIAYNLoss(make_skill_actor(OBS, K, ACT, hidden=(8,)), make_skill_qvalue(OBS, K, ACT, hidden=(8,)),
                     make_discriminator(OBS, K, hidden=(8,)), num_skills=K)


def _diayn_batch():
    skill = torch.eye(K)[torch.randint(K, (8,), generator=torch.Generator().manual_seed(0))]
    return TensorDict({"observation": torch.randn(8, OBS), "skill": skill, "action": torch.rand(8, ACT) * 2 - 1,
                       "next": {"observation": torch.randn(8, OBS), "skill": skill, "reward": torch.zeros(8, 1),
                                "done": torch.zeros(8, 1, dtype=torch.bool),
                                "terminated": torch.zeros(8, 1, dtype=torch.bool)}}, [8])


def _losses():
    return {
        "maml": _maml()[0],
        "diayn": _diayn(),
        "vime": VIMELoss(BayesianDynamics(obs_dim=OBS, act_dim=ACT), dataset_size=8),
        "importance_sampling": ImportanceSamplingLoss(make_gaussian_policy(OBS, ACT, hidden=(8,))),
    }


@pytest.mark.parametrize("name", ["maml", "diayn", "vime", "importance_sampling"])
def test_repr_in_keys_and_out_keys(name):
    loss = _losses()[name]
    text = repr(loss)
    assert type(loss).__name__ in text and "in_keys=" in text
    assert loss.in_keys and all(isinstance(k, (str, tuple)) for k in loss.in_keys)
    assert any(k.startswith("loss_") for k in loss.out_keys)


@pytest.mark.parametrize("name", ["maml", "diayn", "vime", "importance_sampling"])
def test_set_keys_renames_what_in_keys_lists_and_refuses_unknown_names(name):
    loss = _losses()[name]
    field = next(iter(loss._AcceptedKeys.__dataclass_fields__))
    loss.set_keys(**{field: "renamed"})
    assert getattr(loss.tensor_keys, field) == "renamed"
    assert any("renamed" in (k if isinstance(k, tuple) else (k,)) for k in loss.in_keys)
    with pytest.raises(ValueError, match="not an accepted tensordict key"):
        loss.set_keys(no_such_key="x")


def _loss_and_batch(name):
    if name == "vime":
        bnn = BayesianDynamics(obs_dim=OBS, act_dim=ACT)
        g = torch.Generator().manual_seed(0)
        obs, act = torch.randn(8, OBS, generator=g), torch.randn(8, ACT, generator=g)
        bnn.update_normalizer(obs, act, obs + act)
        return VIMELoss(bnn, dataset_size=8), TensorDict({"observation": obs, "action": act,
                                                          ("next", "observation"): obs + act}, [8])
    loss, support, query = _maml()
    if name == "maml":
        return loss, loss.pack(support, query)
    return ImportanceSamplingLoss(loss.policy), support[0]


@pytest.mark.parametrize("name", ["maml", "vime", "importance_sampling"])
def test_out_keys_belong_to_each_instance_and_select_out_keys_filters_the_forward(name):
    loss, batch = _loss_and_batch(name)
    other = _loss_and_batch(name)[0]
    default = list(other.out_keys)
    loss.out_keys.append("extra")
    assert other.out_keys == default and _loss_and_batch(name)[0].out_keys == default
    loss.out_keys = default[:1]
    assert loss.out_keys == default[:1] and other.out_keys == default
    loss.out_keys = default
    selected = [default[0], default[-1]]
    assert loss.select_out_keys(*selected) is loss
    assert loss.out_keys == selected and sorted(loss(batch).keys()) == sorted(selected)
    assert other.out_keys == default and set(other(batch).keys()) == set(default)
    loss.reset_out_keys()
    assert loss.out_keys == default and set(loss(batch).keys()) == set(default)


@pytest.mark.parametrize("name", ["maml", "diayn", "vime", "importance_sampling"])
def test_make_value_estimator_without_arguments_builds_the_default(name):
    loss = _losses()[name]
    assert loss.make_value_estimator() is loss
    assert loss.value_type == type(loss).default_value_estimator


def test_vime_loss_has_no_default_value_estimator_and_attaches_a_given_one():
    loss = VIMELoss(BayesianDynamics(obs_dim=OBS, act_dim=ACT), dataset_size=8)
    assert loss.make_value_estimator() is loss and loss.value_estimator is None and loss.value_type is None
    estimator = TD0Estimator(gamma=0.9, value_network=None)
    assert loss.make_value_estimator(estimator).value_estimator is estimator and loss.value_type is TD0Estimator
    assert loss.make_value_estimator().value_estimator is None and loss.value_type is None
    for value_type in (ValueEstimators.TD0, "no_such_estimator"):
        with pytest.raises(ValueError, match="value_type: got .*; expected None .*ValueEstimatorBase"):
            loss.make_value_estimator(value_type)
    with pytest.raises(ValueError, match=r"hyperparams: got \['gamma'\]"):
        loss.make_value_estimator(gamma=0.9)


def test_soft_update_of_diayn_loss_updates_the_targets_as_on_its_sac_loss():
    loss = _diayn()
    twin = copy.deepcopy(loss)
    updater, reference = SoftUpdate(loss, tau=0.01), SoftUpdate(twin.sac_loss, tau=0.01)
    before = loss.sac_loss.target_qvalue_network_params.clone()
    for each in (loss, twin):
        qvalue = list(each.sac_loss.qvalue_network_params.values(True, True))
        torch.manual_seed(0)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            each(_diayn_batch())["loss_qvalue"].backward()
        assert not [w for w in caught if "No target network updater" in str(w.message)]
        torch.optim.SGD(qvalue, lr=0.1).step()
    updater.step()
    reference.step()
    targets = loss.sac_loss.target_qvalue_network_params
    assert (targets == twin.sac_loss.target_qvalue_network_params).all()
    assert not (targets == before).all() and not (targets == loss.sac_loss.qvalue_network_params.data).all()
    assert loss.target_qvalue_network_params is targets
    assert list(loss.state_dict()) == list(twin.state_dict())  # the targets stay under sac_loss only


def test_maml_forward_reads_renamed_keys_and_gives_the_same_numbers():
    loss, support, query = _maml()
    reference = loss(loss.pack(support, query))
    assert set(reference.keys()) == set(loss.out_keys)
    loss.set_keys(advantage="adv", support="pre", query="post")
    renamed = [td.clone().rename_key_("advantage", "adv") for td in (support, query)]
    packed = loss.pack(*renamed)
    assert set(packed.keys()) == {"pre", "post"}
    out = loss(packed)
    for key in ("loss_objective", "kl", "inner_loss", "return_pre", "return_post"):
        torch.testing.assert_close(out[key], reference[key], rtol=0, atol=0)
    assert ("pre", "adv") in loss.in_keys and ("post", "action_log_prob") in loss.in_keys


def test_maml_forward_with_adapted_params_equals_the_forward_that_adapts():
    loss, support, query = _maml()
    adapted = loss.adapt(support)
    given, redone = loss(loss.pack(support, query, adapted)), loss(loss.pack(support, query))
    torch.testing.assert_close(given["loss_objective"], redone["loss_objective"], rtol=0, atol=0)
    torch.testing.assert_close(given["inner_loss"], redone["inner_loss"])
    assert given["trust_region_kl"].requires_grad and not given["kl"].requires_grad


def test_value_estimators_write_the_advantage_under_the_loss_key():
    loss, support, _ = _maml()
    assert loss.value_estimator.gamma == 0.9
    loss.set_keys(advantage="adv")
    out = loss.value_estimator(support.exclude("advantage"))
    torch.testing.assert_close(out["adv"], support["advantage"])
    with pytest.raises(ValueError, match="value_type: got"):
        loss.make_value_estimator(ValueEstimators.TD0)
    default = ImportanceSamplingLoss(make_gaussian_policy(OBS, ACT, hidden=(8,))).value_estimator
    assert (default.gamma, default.lmbda, default.normalize) == (0.99, 1.0, True)  # MAML-RL's


def test_diayn_forward_gives_every_out_key():
    assert set(_diayn()(_diayn_batch()).keys()) == set(_diayn().out_keys)


def test_importance_sampling_loss_is_one_task_of_mamls_outer_surrogate():
    """VIME's TRPO surrogate equals MAML's outer objective without an inner step, bit for bit."""
    loss, support, _ = _maml()
    batch = support[0]
    with torch.no_grad():
        batch["action_log_prob"] = batch["action_log_prob"] - 0.1  # a different collecting policy: ratio != 1
    maml = MAMLLoss(loss.policy, num_inner_steps=0)
    meta = maml(maml.pack(batch.unsqueeze(0), batch.unsqueeze(0)))
    out = ImportanceSamplingLoss(loss.policy)(batch)
    for key in ("loss_objective", "trust_region_kl"):
        assert torch.equal(out[key], meta[key])
    assert set(out.keys()) == set(ImportanceSamplingLoss(loss.policy).out_keys)


@pytest.mark.parametrize("name", sorted(META_HVPS))
def test_meta_hvp_strategies_drive_a_trpo_step(name):
    loss, support, query = _maml()
    query["advantage"] = torch.randn(query["advantage"].shape, generator=torch.Generator().manual_seed(4))
    trpo = TRPOStep(loss.params, hvp=make_meta_hvp(name, loss, fraction=0.5 if name != "exact" else 1.0,
                                                    generator=torch.Generator().manual_seed(0)), max_kl=0.05)
    batch = loss.pack(support, query)

    def closure():
        out = loss(batch)
        return out["loss_objective"], out["trust_region_kl"]

    info = trpo(closure, batch=batch)
    assert info["backtracks"] >= 1 and info["grad_norm"] > 0
    with pytest.raises(ValueError, match="trpo.hvp: got 'fisher'"):
        make_meta_hvp("fisher", loss)
    with pytest.raises(TypeError, match="hvp: got"):
        TRPOStep(loss.params, hvp="exact")
    assert repr(KLHessian()) == "KLHessian(closure KL)"


# Every key of every loss renamed, from collection through the value estimator to a trained step: the renamed run
# gives the default run's numbers bit for bit, and nothing reads a default name.

def _renamed(td, names):
    """``td`` with each entry named in ``names`` (default -> new, root or nested) moved to its new name."""
    for old, new in names.items():
        if old in td.keys(True):
            td.rename_key_(old, new)
    return td


def _fields(loss_or_estimator):
    return set(loss_or_estimator._AcceptedKeys.__dataclass_fields__)


MAML_KEYS = {"support": "pre", "query": "post", "adapted": "phi", "action": "act", "action_log_prob": "act_lp",
             "advantage": "adv", "loc": "mu", "scale": "sigma", "mask": "valid", "reward": "rew", "done": "end"}
# the value estimator's own keys (the loss forwards those it shares: advantage, mask, reward, done)
ESTIMATOR_KEYS = {"observation": "obs", "step_count": "t", "value_target": "ret", "value": "baseline"}
# what collection writes, under the names above
COLLECTED = {"observation": "obs", ("next", "observation"): ("next", "obs"), "step_count": "t",
             ("next", "step_count"): ("next", "t"), "action": "act", "action_log_prob": "act_lp", "loc": "mu",
             "scale": "sigma", "mask": "valid", ("next", "reward"): ("next", "rew"), ("next", "done"): ("next", "end")}


def _collection(renamed):
    """point_nav's oracle tasks, a policy reading ``"obs"`` (a RenameTransform on the env) or ``"observation"``, and
    a ``collect(params) -> batch`` whose entries carry the renamed keys (``COLLECTED``) or the defaults."""
    torch.manual_seed(0)
    proposal = make_proposal("oracle", "point_nav", num_tasks=T, trajectories_per_task=N, horizon=H)
    proposal.resample(torch.Generator().manual_seed(0))
    env = proposal.env
    if renamed:
        env.append_transform(RenameTransform(["observation"], ["obs"]))
    policy = make_gaussian_policy(OBS, ACT, hidden=(8,), seed=0, in_keys=["obs" if renamed else "observation"])

    def collect_batch(params=None, *, with_mask=True):
        td = collect(env, policy, num_tasks=T, horizon=H, params=params)
        td = td if with_mask else td.exclude("mask")  # then the value estimator writes it
        return _renamed(td, {k: v for k, v in COLLECTED.items() if k != "observation"}) if renamed else td

    return policy, collect_batch


def _maml_step(renamed, hvp):
    policy, collect_batch = _collection(renamed)
    loss = MAMLLoss(policy, inner_lr=0.5).make_value_estimator(gamma=0.9)
    if renamed:
        loss.set_keys(**MAML_KEYS)
        loss.value_estimator.set_keys(**ESTIMATOR_KEYS)
    support = loss.value_estimator(collect_batch(with_mask=False))
    adapted = loss.adapt(support)
    query = loss.value_estimator(collect_batch(adapted.detach()))
    first = loss(loss.pack(support, query, adapted))
    batch = loss.pack(support, query)

    def closure():
        out = loss(batch)
        return out["loss_objective"], out["trust_region_kl"]

    strategy = make_meta_hvp(hvp, loss, fraction=0.5 if hvp != "exact" else 1.0,
                             generator=torch.Generator().manual_seed(0))
    info = TRPOStep(loss.params, hvp=strategy, max_kl=0.05, max_backtracks=40)(
        closure, batch=batch, initial=(first["loss_objective"], first["trust_region_kl"]))
    return batch, first, info, [p.detach().clone() for p in policy.parameters()]


@pytest.mark.parametrize("hvp", sorted(META_HVPS))
def test_maml_with_every_key_renamed_collects_estimates_and_trains_as_with_the_defaults(hvp):
    assert _fields(MAMLLoss) == set(MAML_KEYS)
    loss = MAMLLoss(make_gaussian_policy(OBS, ACT, hidden=(8,))).make_value_estimator()
    assert _fields(loss.value_estimator) == {"advantage", "mask", "reward", "done"} | set(ESTIMATOR_KEYS)
    batch, out, info, params = _maml_step(True, hvp)
    default_batch, default_out, default_info, default_params = _maml_step(False, hvp)
    assert set(batch.keys()) == {"pre", "post"}
    defaults = {*COLLECTED, "advantage", "value_target", "state_value"}
    for part in ("pre", "post"):
        assert not defaults & set(batch[part].keys(True)), part
        torch.testing.assert_close(batch[part, "adv"], default_batch["support" if part == "pre" else "query",
                                                                      "advantage"], rtol=0, atol=0)
    for key in out.keys(True, True):
        assert torch.equal(out[key], default_out[key]), key
    assert info["accepted"] == 1.0 and info["step_norm"] > 0
    assert info["surrogate_after"] == default_info["surrogate_after"]
    assert all(torch.equal(p, q) for p, q in zip(params, default_params))


def test_renaming_the_mask_reaches_the_value_estimator_and_the_inner_step():
    policy, collect_batch = _collection(False)
    loss = MAMLLoss(policy).make_value_estimator()
    loss.set_keys(mask="valid")
    support = loss.value_estimator(collect_batch(with_mask=False))
    assert "valid" in support.keys(True) and "mask" not in support.keys(True)
    assert loss.adapt(support).batch_size == (T,)


def _importance_sampling_step(renamed):
    policy, collect_batch = _collection(renamed)
    loss = ImportanceSamplingLoss(policy).make_value_estimator(gamma=0.9)
    names = {k: MAML_KEYS[k] for k in _fields(ImportanceSamplingLoss)}
    if renamed:
        loss.set_keys(**names)
        loss.value_estimator.set_keys(reward="rew", done="end", **ESTIMATOR_KEYS)
    batch = loss.value_estimator(collect_batch()[0])  # one task's trajectories [N, H]
    batch.set(names["action_log_prob"] if renamed else "action_log_prob",
              batch.get(names["action_log_prob"] if renamed else "action_log_prob") - 0.1)

    def closure():
        out = loss(batch)
        return out["loss_objective"], out["trust_region_kl"]

    first = loss(batch)
    info = TRPOStep(TensorDict.from_module(policy), max_kl=0.05, max_backtracks=40)(closure)
    return first, info, [p.detach().clone() for p in policy.parameters()]


def test_importance_sampling_loss_with_every_key_renamed_trains_as_with_the_defaults():
    (out, info, params), (default_out, _, default_params) = _importance_sampling_step(True), \
        _importance_sampling_step(False)
    for key in out.keys(True, True):
        assert torch.equal(out[key], default_out[key]), key
    assert info["accepted"] == 1.0 and all(torch.equal(p, q) for p, q in zip(params, default_params))


def _vime_step(renamed):
    names = {"observation": "s", "action": "a", "next_observation": ("next", "s")}
    torch.manual_seed(0)
    bnn = BayesianDynamics(obs_dim=OBS, act_dim=ACT)
    g = torch.Generator().manual_seed(0)
    obs, act = torch.randn(8, OBS, generator=g), torch.randn(8, ACT, generator=g)
    bnn.update_normalizer(obs, act, obs + act)
    loss = VIMELoss(bnn, dataset_size=8)
    batch = TensorDict({"observation": obs, "action": act, ("next", "observation"): obs + act}, [8])
    if renamed:
        assert _fields(loss) == set(names)
        loss.set_keys(**names)
        batch = _renamed(batch, {"observation": "s", "action": "a", ("next", "observation"): ("next", "s")})
    return _sgd_step(loss, batch, ["loss_dynamics"])


def _sgd_step(loss, batch, terms):
    """``(out, parameters before, parameters after)`` of one SGD step on the sum of ``terms`` (random draws seeded)."""
    before = [p.detach().clone() for p in loss.parameters()]
    torch.manual_seed(1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # DIAYN's "no target network updater": none is needed for one step
        out = loss(batch)
    sum(out[k].sum() for k in terms).backward()
    torch.optim.SGD(loss.parameters(), lr=0.1).step()
    return out, before, [p.detach().clone() for p in loss.parameters()]


DIAYN_KEYS = {"skill": "z", "discriminator_observation": "obs", "action": "act", "log_prob": "lp", "reward": "rew",
              "done": "end", "terminated": "term", "state_action_value": "q", "priority": "err"}


def _diayn_networks(keys):
    """Actor, twin Q and discriminator reading ``keys`` (the Q-network's action input and value output too)."""
    torch.manual_seed(0)
    actor = make_skill_actor(OBS, K, ACT, hidden=(8,), observation_key=keys["discriminator_observation"],
                             skill_key=keys["skill"])
    net = MLP(in_features=OBS + K + ACT, out_features=1, num_cells=[8], activation_class=torch.nn.ReLU)
    qvalue = ValueOperator(net, in_keys=[keys["discriminator_observation"], keys["skill"], keys["action"]],
                           out_keys=[keys["state_action_value"]])
    return actor, qvalue, make_discriminator(OBS, K, hidden=(8,), in_key=keys["discriminator_observation"])


def _diayn_step(renamed):
    keys = DIAYN_KEYS if renamed else {name: name for name in DIAYN_KEYS} | {
        "discriminator_observation": "observation", "log_prob": "action_log_prob", "priority": "td_error"}
    loss = DIAYNLoss(*_diayn_networks(keys), num_skills=K).make_value_estimator(gamma=0.9)
    batch = _diayn_batch()
    if renamed:
        assert _fields(DIAYNLoss) == set(DIAYN_KEYS)
        loss.set_keys(**DIAYN_KEYS)
        batch = _renamed(batch, {"observation": "obs", "skill": "z", "action": "act", ("next", "observation"):
                                 ("next", "obs"), ("next", "skill"): ("next", "z"), ("next", "reward"): ("next", "rew"),
                                 ("next", "done"): ("next", "end"), ("next", "terminated"): ("next", "term")})
    return _sgd_step(loss, batch, ["loss_actor", "loss_qvalue", "loss_discriminator"])


def _stacked_diayn_step(renamed):
    names = {"observation": "obs", "skill": "z", "discriminator_observation": "obs", "action": "act",
             "noise": "eps", "terminated": "term"}
    losses = [DIAYNLoss(*_diayn_networks({"discriminator_observation": "observation", "skill": "skill",
                                          "action": "action", "state_action_value": "state_action_value"}),
                        num_skills=K) for _ in range(2)]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # reading the targets of a loss without an updater
        loss = StackedDIAYNLoss.from_losses(losses, gamma=0.9)
    batch = torch.stack([_diayn_batch(), _diayn_batch()])
    g = torch.Generator().manual_seed(2)
    batch["action_noise"], batch["next", "action_noise"] = (torch.randn(2, 8, ACT, generator=g) for _ in range(2))
    if renamed:
        assert _fields(StackedDIAYNLoss) == set(names)
        loss.set_keys(**names)
        batch = _renamed(batch, {"observation": "obs", "skill": "z", "action": "act", "action_noise": "eps",
                                 ("next", "observation"): ("next", "obs"), ("next", "skill"): ("next", "z"),
                                 ("next", "action_noise"): ("next", "eps"), ("next", "terminated"): ("next", "term")})
    return _sgd_step(loss, batch, ["loss_actor", "loss_qvalue", "loss_discriminator"])


@pytest.mark.parametrize("step", [_vime_step, _diayn_step, _stacked_diayn_step], ids=["vime", "diayn", "stacked"])
def test_losses_with_every_key_renamed_train_a_step_as_with_the_defaults(step):
    (out, before, after), (default_out, _, default_after) = step(True), step(False)
    for key in out.keys(True, True):
        assert torch.equal(out[key], default_out[key]), key
    assert all(torch.equal(p, q) for p, q in zip(after, default_after))
    assert any(not torch.equal(p, q) for p, q in zip(before, after))
