"""Every loss honours TorchRL's contract: forward(td), set_keys, in_keys / out_keys (per instance, select_out_keys),
repr, make_value_estimator, target updaters built on the loss itself."""
import copy
import warnings

import pytest
import torch
from tensordict import TensorDict
from torchrl.objectives import SoftUpdate
from torchrl.objectives.utils import ValueEstimators
from torchrl.objectives.value import TD0Estimator

from umrl.modules.bnn import BayesianDynamics
from umrl.modules.discriminator import make_discriminator
from umrl.modules.policy import make_gaussian_policy
from umrl.modules.sac import make_skill_actor, make_skill_qvalue
from umrl.objectives import DIAYNLoss, ImportanceSamplingLoss, MAMLLoss, VIMELoss
from umrl.objectives.maml_hvp import META_HVPS, make_meta_hvp
from umrl.optim import KLHessian, TRPOStep

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
    surrogate, kl = maml.objective_and_kl(batch.unsqueeze(0), batch.unsqueeze(0))
    out = ImportanceSamplingLoss(loss.policy)(batch)
    assert torch.equal(out["loss_objective"], surrogate) and torch.equal(out["trust_region_kl"], kl)
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
