"""DIAYN: "Diversity is All You Need" (Eysenbach et al., 2018, https://arxiv.org/abs/1802.06070).

A skill-conditioned policy pi(a|s,z) is trained by SAC on the pseudo-reward r = log D(z|s) - log p(z) while a
discriminator D(z|s) learns to tell the skills apart from the states they visit. UMRL (Gupta et al., 2018,
https://arxiv.org/abs/1806.04640) keeps D as a task proposal: r_z(s) = log D(z|s) defines one task per skill.
"""
from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import CudaGraphModule, TensorDictModule, TensorDictModuleBase, TensorDictParams
from tensordict.utils import NestedKey, unravel_key
from torchrl._utils import compile_with_warmup
from torchrl.data import TensorSpec
from torchrl.modules import ProbabilisticActor
from torchrl.objectives import LossModule, SACLoss, SoftUpdate
from torchrl.objectives.utils import ValueEstimators

from umrl.modules.discriminator import discriminator_logits
from umrl.transforms.discriminator_reward import check_skills, skill_reward
from umrl.validation import check_float, check_keys, check_positive

__all__ = ["DIAYNLoss", "DIAYNUpdate", "UpdateRunner", "check_capturable", "make_diayn_optimizers"]


class DIAYNLoss(LossModule):
    """SAC on discriminator pseudo-rewards (TorchRL's :class:`~torchrl.objectives.SACLoss`) + D's cross-entropy.

    At every call the batch's ``("next", "reward")`` is recomputed with the *current* discriminator (on a shallow
    copy: the input tensordict is not modified), as DIAYN's reference code does, so replay samples never carry stale
    rewards. The discriminator is trained on the same state its reward scores (``discriminator_observation``: s_t by default,
    as in DIAYN's reference code) with the skill index as label.

    Args:
        actor_network (ProbabilisticActor): pi(a|s,z), e.g. :func:`umrl.modules.sac.make_skill_actor`.
        qvalue_network (TensorDictModule): Q(s,z,a), e.g. :func:`umrl.modules.sac.make_skill_qvalue`; SACLoss
            makes ``num_qvalue_nets`` independently initialised copies (and their target copies).
        discriminator (TensorDictModuleBase): D, one in_key (observation) and one out_key (logits [*B, K]), e.g.
            :func:`umrl.modules.discriminator.make_discriminator`.

    Keyword Args:
        num_skills (int): K >= 2 (uniform prior p(z) = 1/K).
        alpha_init (float): entropy coefficient. Defaults to 0.1 (DIAYN's entropy scale).
        fixed_alpha (bool): keep alpha at ``alpha_init`` (paper). Defaults to ``True``; then ``loss_alpha`` is 0.
        target_entropy (float or "auto"): for a learned alpha; ``"auto"`` needs ``action_spec``.
        action_spec (TensorSpec, optional): unbatched action spec, used by ``target_entropy="auto"``.
        num_qvalue_nets (int): twin Q by default (2).
        loss_function (str): Q regression loss. Defaults to ``"l2"`` (the reference SAC's MSE).

    Returns (``forward``): a TensorDict with ``loss_actor``, ``loss_qvalue``, ``loss_alpha``,
    ``loss_discriminator`` (each reaches only its own parameters) and detached diagnostics ``alpha``,
    ``entropy``, ``discriminator_accuracy`` (fraction of the batch whose argmax D(s) is the true skill) and
    ``pseudo_reward`` (mean relabelled reward).

    The discount is set as in TorchRL: ``loss.make_value_estimator(gamma=0.99)`` (TD(0), gamma 0.99 by default).
    Target Q-networks are updated with ``SoftUpdate(loss, tau=0.01)``, which updates the same targets as
    ``SoftUpdate(loss.sac_loss, tau=0.01)``.

    Examples:
        >>> import torch
        >>> from tensordict import TensorDict
        >>> from umrl.modules.discriminator import make_discriminator
        >>> from umrl.modules.sac import make_skill_actor, make_skill_qvalue
        >>> obs_dim, act_dim, K, B = 2, 2, 4, 8
        >>> loss = DIAYNLoss(make_skill_actor(obs_dim, K, act_dim, hidden=(16,)),
        ...                  make_skill_qvalue(obs_dim, K, act_dim, hidden=(16,)),
        ...                  make_discriminator(obs_dim, K, hidden=(16,)), num_skills=K)
        >>> skill = torch.eye(K)[torch.randint(K, (B,))]
        >>> data = TensorDict({
        ...     "observation": torch.randn(B, obs_dim), "skill": skill, "action": torch.rand(B, act_dim) * 2 - 1,
        ...     "next": {"observation": torch.randn(B, obs_dim), "skill": skill, "reward": torch.zeros(B, 1),
        ...              "done": torch.zeros(B, 1, dtype=torch.bool),
        ...              "terminated": torch.zeros(B, 1, dtype=torch.bool)},
        ... }, [B])
        >>> out = loss(data)
        >>> sorted(k for k in out.keys() if k.startswith("loss_"))
        ['loss_actor', 'loss_alpha', 'loss_discriminator', 'loss_qvalue']
        >>> sum(out[k] for k in out.keys() if k.startswith("loss_")).backward()
    """

    @dataclass
    class _AcceptedKeys:
        """Tensordict keys read by the loss (change them with ``set_keys``).

        Attributes:
            skill (NestedKey): one-hot skill [*B, K]. Defaults to ``"skill"``.
            discriminator_observation (NestedKey): the state D scores and is trained on. Defaults to
                ``"observation"`` (s_t, the state the action was taken in, as DIAYN's reference code).
            action (NestedKey): Defaults to ``"action"``.
            log_prob (NestedKey): Defaults to ``"action_log_prob"``.
            reward (NestedKey): pseudo-reward, written under ``"next"`` on the copy. Defaults to ``"reward"``.
            done (NestedKey): Defaults to ``"done"``.
            terminated (NestedKey): Defaults to ``"terminated"``; bootstrapping stops only at termination, so
                time-limit truncation keeps its bootstrap.
            state_action_value (NestedKey): Q output. Defaults to ``"state_action_value"``.
            priority (NestedKey): SAC's TD error key (written on the copy only). Defaults to ``"td_error"``.
        """

        skill: NestedKey = "skill"
        discriminator_observation: NestedKey = "observation"
        action: NestedKey = "action"
        log_prob: NestedKey = "action_log_prob"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        state_action_value: NestedKey = "state_action_value"
        priority: NestedKey = "td_error"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    default_value_estimator = ValueEstimators.TD0
    _SAC_KEYS = ("action", "log_prob", "reward", "done", "terminated", "state_action_value", "priority")

    def __init__(
        self,
        actor_network: ProbabilisticActor,
        qvalue_network: TensorDictModule,
        discriminator: TensorDictModuleBase,
        *,
        num_skills: int,
        alpha_init: float = 0.1,
        fixed_alpha: bool = True,
        target_entropy: float | str = "auto",
        action_spec: TensorSpec | None = None,
        num_qvalue_nets: int = 2,
        loss_function: str = "l2",
    ):
        if num_skills < 2:
            raise ValueError(f"num_skills must be >= 2, got {num_skills}.")
        check_positive("alpha_init", alpha_init)
        if target_entropy != "auto":
            check_float("target_entropy", target_entropy)
        super().__init__()
        self.num_skills = num_skills
        self.fixed_alpha = fixed_alpha
        self.sac_loss = SACLoss(
            actor_network,
            qvalue_network,
            num_qvalue_nets=num_qvalue_nets,
            loss_function=loss_function,
            alpha_init=alpha_init,
            fixed_alpha=fixed_alpha,
            target_entropy=0.0 if fixed_alpha else target_entropy,
            action_spec=action_spec,
        )
        # SACLoss registers its target-entropy buffer lazily; materialise it so state dicts round-trip.
        _ = self.sac_loss.target_entropy
        # one record of which networks have a target updater, so an updater built on either loss silences both
        self._has_update_associated = self.sac_loss._has_update_associated
        self.discriminator = discriminator
        self._forward_value_estimator_keys()

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        self.sac_loss.set_keys(**{name: getattr(self.tensor_keys, name) for name in self._SAC_KEYS})
        written = unravel_key(("next", self.tensor_keys.reward))  # the relabelled reward: written, never read
        self._required_keys = [key for key in self.in_keys if key != written]
        # the error texts, formatted once here rather than on every update
        self._batch_expected = f"a batch of transitions with {self._required_keys}"
        self._skill_name = f"tensordict[{self.tensor_keys.skill!r}]"

    def make_value_estimator(self, value_type: ValueEstimators = None, **hyperparams):
        """Sets SAC's value estimator (e.g. ``make_value_estimator(gamma=0.99)``)."""
        self.sac_loss.make_value_estimator(value_type, **hyperparams)
        return self

    @property
    def qvalue_network_params(self) -> TensorDictParams:
        """SAC's Q-network parameters, the source of :attr:`target_qvalue_network_params`."""
        return self.sac_loss.qvalue_network_params

    @property
    def target_qvalue_network_params(self) -> TensorDictParams:
        """SAC's target Q-network parameters (held by :attr:`sac_loss`)."""
        return self.sac_loss.target_qvalue_network_params

    def named_children(self) -> Iterator[tuple[str, torch.nn.Module]]:
        """The submodules, then SAC's target Q-parameters as ``target_qvalue_network_params``: the name TorchRL's
        target updaters (:class:`~torchrl.objectives.SoftUpdate`) look for among a loss's children. ``state_dict``
        and ``named_modules`` keep them under ``sac_loss`` only."""
        yield from super().named_children()
        yield "target_qvalue_network_params", self.sac_loss.get_submodule("target_qvalue_network_params")

    @property
    def in_keys(self) -> list[NestedKey]:
        keys = set(self.sac_loss.in_keys) | {
            unravel_key(self.tensor_keys.skill), unravel_key(self.tensor_keys.discriminator_observation)
        }
        return sorted(keys, key=str)

    @property
    def out_keys(self) -> list[str]:
        """SAC's outputs (``loss_actor``, ``loss_qvalue``, ``loss_alpha``, ``alpha``, ``entropy``) and the
        discriminator's (``loss_discriminator``, ``discriminator_accuracy``, ``pseudo_reward``)."""
        return [*self.sac_loss.out_keys, "loss_discriminator", "discriminator_accuracy", "pseudo_reward"]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        check_keys("tensordict", tensordict, self._required_keys, self._batch_expected)
        skill = tensordict.get(self.tensor_keys.skill)
        check_skills(self._skill_name, skill, self.num_skills)
        # One forward of D serves both its loss and the relabelled reward (the reward sees detached logits).
        logits = discriminator_logits(self.discriminator, tensordict.get(self.tensor_keys.discriminator_observation))
        reward = skill_reward(logits.detach(), skill)
        data = tensordict.copy()  # shallow: the relabelled reward and SAC's td_error land on the copy only
        data.set(unravel_key(("next", self.tensor_keys.reward)), reward)
        out = self.sac_loss(data)
        if self.fixed_alpha:
            out.set("loss_alpha", torch.zeros((), device=out["loss_actor"].device))
        label = skill.argmax(-1)
        out.set("loss_discriminator", torch.nn.functional.cross_entropy(logits.flatten(0, -2), label.flatten()))
        out.set("discriminator_accuracy", (logits.argmax(-1) == label).float().mean().detach())
        out.set("pseudo_reward", reward.mean())
        return out

#: ``torch.compile`` modes accepted by :class:`DIAYNUpdate`'s ``compile``.
COMPILE_MODES = ("default", "reduce-overhead", "max-autotune", "max-autotune-no-cudagraphs")


def make_diayn_optimizers(
    loss: DIAYNLoss, *, lr: float, discriminator_lr: float, capturable: bool = False
) -> dict[str, torch.optim.Optimizer]:
    """Adam for each parameter group of a :class:`DIAYNLoss`: ``{"actor", "qvalue", "discriminator"[, "alpha"]}``.

    ``"alpha"`` is present only for a learned alpha (``fixed_alpha=False``). ``capturable=True`` keeps Adam's step
    counters on the parameters' device, which CUDA graphs need (:class:`DIAYNUpdate` with ``cudagraphs=True``).
    """
    lr, discriminator_lr = check_positive("lr", lr), check_positive("discriminator_lr", discriminator_lr)
    sac = loss.sac_loss
    adam = {"capturable": capturable}
    optimizers = {
        "actor": torch.optim.Adam(list(sac.actor_network_params.values(True, True)), lr=lr, **adam),
        "qvalue": torch.optim.Adam(list(sac.qvalue_network_params.values(True, True)), lr=lr, **adam),
        "discriminator": torch.optim.Adam(list(loss.discriminator.parameters()), lr=discriminator_lr, **adam),
    }
    if not loss.fixed_alpha:
        optimizers["alpha"] = torch.optim.Adam([sac.log_alpha], lr=lr, **adam)
    return optimizers


def _distribution_kwargs_to(module: torch.nn.Module, device: torch.device) -> None:
    """Put the float and tensor values of every submodule's ``distribution_kwargs`` (TanhNormal's ``low``/``high``)
    on ``device`` as tensors, in place. The distribution turns host numbers into device tensors at every call, a
    host-to-device copy that CUDA graph capture refuses; values, dtypes (the default float) and results are unchanged.
    """
    for sub in module.modules():
        kwargs = getattr(sub, "distribution_kwargs", None)
        if kwargs:
            sub.distribution_kwargs = {
                key: torch.as_tensor(value, device=device) if isinstance(value, (float, torch.Tensor)) else value
                for key, value in kwargs.items()}


class DIAYNUpdate:
    """One DIAYN gradient update: loss -> backward -> every optimiser's step -> soft update of the target Q-nets.

    The one place a SAC + discriminator update happens, modelled on TorchRL's ``sota-implementations/sac``: the same
    function runs eagerly, under ``torch.compile`` and/or captured in a CUDA graph
    (:class:`tensordict.nn.CudaGraphModule`). It never synchronises with the host, so a GPU runs updates back to
    back; check the returned losses for finiteness once per batch of updates, not per update.

    Args:
        loss (DIAYNLoss): the loss; its parameters (and the batches passed in) live on one device.
        optimizers (mapping of str to Optimizer): e.g. :func:`make_diayn_optimizers`; each is stepped and zeroed
            (``set_to_none``) once per update.

    Keyword Args:
        tau (float): Polyak rate of the target Q-networks (TorchRL's :class:`~torchrl.objectives.SoftUpdate`).
        compile (bool or str): ``torch.compile`` the update (after one eager warm-up call). ``True`` picks TorchRL's
            mode rule (``"default"`` with CUDA graphs, else ``"reduce-overhead"``); a string is the mode. Compiled
            updates draw SAC's action noise from inductor's RNG, so they do not reproduce eager numbers bit for bit.
        cudagraphs (bool): capture the update in a CUDA graph (CUDA only; the optimisers must be ``capturable``).
            Every batch must then have the same shape and device. The loss's distribution bounds (the actor's
            ``distribution_kwargs``) are moved to the device as tensors, since capture cannot copy host numbers.

    ``update(batch)`` takes a replay sample (the keys :class:`DIAYNLoss` reads, batch [B]) and returns the loss's
    output TensorDict, detached (``loss_*``, ``alpha``, ``entropy``, ``discriminator_accuracy``, ``pseudo_reward``).

    Examples:
        >>> from tensordict import TensorDict
        >>> from umrl.modules.discriminator import make_discriminator
        >>> from umrl.modules.sac import make_skill_actor, make_skill_qvalue
        >>> K = 4
        >>> loss = DIAYNLoss(make_skill_actor(2, K, 2, hidden=(16,)), make_skill_qvalue(2, K, 2, hidden=(16,)),
        ...                  make_discriminator(2, K, hidden=(16,)), num_skills=K)
        >>> update = DIAYNUpdate(loss, make_diayn_optimizers(loss, lr=1e-3, discriminator_lr=1e-3), tau=0.01)
        >>> skill = torch.eye(K)[torch.randint(K, (8,))]
        >>> batch = TensorDict({
        ...     "observation": torch.randn(8, 2), "skill": skill, "action": torch.rand(8, 2) * 2 - 1,
        ...     "next": {"observation": torch.randn(8, 2), "skill": skill, "reward": torch.zeros(8, 1),
        ...              "done": torch.zeros(8, 1, dtype=torch.bool),
        ...              "terminated": torch.zeros(8, 1, dtype=torch.bool)}}, [8])
        >>> update(batch)["loss_discriminator"].requires_grad
        False
    """

    def __init__(
        self,
        loss: DIAYNLoss,
        optimizers: Mapping[str, torch.optim.Optimizer],
        *,
        tau: float,
        compile: bool | str = False,
        cudagraphs: bool = False,
    ):
        device = next(loss.parameters()).device
        check_capturable(optimizers, cudagraphs, device)
        if cudagraphs:
            _distribution_kwargs_to(loss.sac_loss.actor_network, device)  # held outside the module tree
        self.loss = loss
        self.optimizers = dict(optimizers)
        self.target_updater = SoftUpdate(loss.sac_loss, tau=check_float("tau", tau, ge=0, le=1))
        self.runner = UpdateRunner(self._step, compile=compile, cudagraphs=cudagraphs, device=device)
        self.compile_mode, self.cudagraphs = self.runner.compile_mode, cudagraphs

    def _step(self, batch: TensorDictBase) -> TensorDictBase:
        out = self.loss(batch)
        sum(value for key, value in out.items() if key.startswith("loss_")).backward()
        for optimizer in self.optimizers.values():
            optimizer.step()
            optimizer.zero_grad(set_to_none=True)
        self.target_updater.step()
        return out.detach()

    def __call__(self, batch: TensorDictBase) -> TensorDictBase:
        return self.runner(batch)


def check_capturable(optimizers: Mapping[str, torch.optim.Optimizer], cudagraphs: bool, device: torch.device) -> None:
    """Refuse ``cudagraphs=True`` off CUDA or with optimisers that are not ``capturable``."""
    if not cudagraphs:
        return
    if device.type != "cuda":
        raise ValueError(f"cudagraphs=True needs the loss on a CUDA device, its parameters are on {device}; "
                         "pass cudagraphs=False (recipe: optim.cudagraphs=false).")
    eager = [name for name, opt in optimizers.items()
             if not all(group.get("capturable", False) for group in opt.param_groups)]
    if eager:
        raise ValueError(f"cudagraphs=True needs capturable optimisers; {eager} are not: build them with "
                         "capturable=True.")


class UpdateRunner:
    """Runs one update function ``step(batch) -> TensorDict`` eagerly, under ``torch.compile`` and/or captured in a
    CUDA graph (:class:`tensordict.nn.CudaGraphModule`), modelled on TorchRL's ``sota-implementations/sac``.

    ``compile``: ``True`` picks TorchRL's mode rule (``"default"`` with CUDA graphs or a ``compile_target``, else
    ``"reduce-overhead"``), a string is the mode (one of :data:`COMPILE_MODES`). ``compile_target``: a function
    ``step`` calls, compiled instead of ``step`` itself (:attr:`compiled_target`, None when ``compile`` is off), for
    an update whose rest gains nothing from compiling. Outputs of static CUDA-graph buffers are cloned, so they
    survive the next call; a compilation failure is re-raised naming the switch that turns it off.
    """

    def __init__(self, step, *, compile: bool | str = False, cudagraphs: bool = False,
                 device: torch.device | str = "cpu", compile_target=None):
        if isinstance(compile, str) and compile not in COMPILE_MODES:
            raise ValueError(f"compile mode {compile!r} is not one of {COMPILE_MODES} (or True / False).")
        self.compile_mode = None
        if compile:
            self.compile_mode = compile if isinstance(compile, str) else (
                "default" if cudagraphs or compile_target is not None else "reduce-overhead")
        # CUDA graphs (ours, or inductor's in these modes) reuse their output buffers at the next call
        self._static_outputs = cudagraphs or self.compile_mode in ("reduce-overhead", "max-autotune")
        self.compiled_target = None
        if self.compile_mode is not None and compile_target is not None:
            self.compiled_target = torch.compile(compile_target, dynamic=False, mode=self.compile_mode)
        elif self.compile_mode is not None:
            step = compile_with_warmup(step, mode=self.compile_mode, warmup=1)
        if cudagraphs:
            step = CudaGraphModule(step, in_keys=[], out_keys=[], warmup=5, device=torch.device(device))
        self._update = step

    def __call__(self, batch: TensorDictBase) -> TensorDictBase:
        if self._static_outputs:
            torch.compiler.cudagraph_mark_step_begin()
        try:
            out = self._update(batch)
        except (torch._dynamo.exc.TorchDynamoException, torch._inductor.exc.InductorError) as err:
            raise RuntimeError(
                f"torch.compile failed on the DIAYN update (compile={self.compile_mode!r}): {err}\n"
                "Turn it off with compile=False (recipe: optim.compile=false)."
            ) from err
        return out.clone() if self._static_outputs else out
