"""Schema of ``umrl/suite/config/suite.yaml`` and its profiles (the benchmark suite)."""
# ruff: noqa: RUF009  (the field helpers of umrl.configs.validate return dataclasses.field(...) objects)
from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from string import Formatter
from typing import Any

from umrl.checkpoints import load_diayn_checkpoint, load_maml_checkpoint, load_vime_checkpoint
from umrl.checkpoints.folder import Checkpointer
from umrl.configs.common import LoggerConfig, cudagraphs_errors
from umrl.configs.diayn import DIAYNConfig
from umrl.configs.maml import MAMLConfig, num_skills_errors
from umrl.configs.memory import Allocation, allocation_errors, step_bytes
from umrl.configs.validate import (
    boolean,
    check_partial,
    checked,
    choice_list,
    device,
    int_list,
    integer,
    mapping,
    name,
    number,
    number_list,
    string,
    writable_dir,
)
from umrl.configs.vime import VIMEConfig
from umrl.envs import ENV_NAMES
from umrl.envs.user_envs import import_env_module
from umrl.metatest.methods import METHODS, PROPOSALS, Pretraining
from umrl.metatest.protocol import SGD_SCHEDULES
from umrl.validation import (
    MAX_THREADS,
    SEED_MAX,
    InvalidType,
    InvalidValue,
    check_choice,
    check_list,
    check_seed,
    check_str,
)

RECIPE_SCHEMAS = {"diayn": DIAYNConfig, "maml": MAMLConfig, "vime": VIMEConfig}
"""The schema each ``pretrain.<recipe>.overrides`` is checked against."""
MAML_METHODS = tuple(m.name for m in METHODS.values() if m.pretraining and m.pretraining.recipe == "maml")
BASELINE_METHODS = tuple(m for m in METHODS if m not in MAML_METHODS)
"""Methods the ablation can draw beside the MAML checkpoints: the ones not meta-trained (one cell per seed)."""


def check_reuse(name: str, value: Any) -> str | dict | None:
    """``null``, a path template (``{env}``, ``{seed}``, ``{proposal}``) or (maml) a mapping proposal -> template."""
    expected = "null, a path template with {env} {seed} {proposal}, or a mapping from proposal to template"
    if value is None:
        return None
    if isinstance(value, str):
        return _check_template(name, value)
    if not isinstance(value, Mapping):
        raise InvalidType(name, value, expected)
    unknown = [k for k in value if k not in PROPOSALS]
    if unknown:
        raise InvalidValue(name, value, f"proposal keys from {', '.join(map(repr, PROPOSALS))}",
                           note=f"unknown keys {unknown}")
    for key, template in value.items():
        if template is not None:
            _check_template(f"{name}.{key}", template)
    return dict(value)


def check_sgd_schedule(name: str, value: Any) -> str | list[str]:
    """One of :data:`~umrl.metatest.protocol.SGD_SCHEDULES` or a non-empty list of distinct ones."""
    if isinstance(value, str):
        return check_choice(name, value, SGD_SCHEDULES)
    what = f"names from {', '.join(map(repr, SGD_SCHEDULES))}"
    return check_list(name, value, partial(check_choice, choices=SGD_SCHEDULES), min_len=1, unique=True, what=what)


def check_pretrain_seeds(name: str, value: Any) -> int | list[int] | None:
    """``null`` (each meta-test seed's own), one seed (shared) or a list of seeds (one per seed); seeds as
    :func:`~umrl.validation.check_seed` accepts them."""
    if value is None or isinstance(value, int) and not isinstance(value, bool):
        return value if value is None else check_seed(name, value)
    return check_list(name, value, check_seed, what=f"integers in [0, {SEED_MAX}] (one per entry of seeds)")


RAY_ADDRESS = re.compile(r"(ray://)?(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.-]+):([0-9]{1,5})")
"""``host:port`` (a cluster's GCS) or ``ray://host:port`` (Ray Client); an IPv6 host in brackets."""


def check_ray_address(name: str, value: Any) -> str:
    """``auto`` (the running cluster), ``local`` (start Ray here), ``host:port`` or ``ray://host:port``: the addresses
    ``ray.init`` connects to (:data:`RAY_ADDRESS`)."""
    expected = "'auto', 'local', host:port or ray://host:port (port 1-65535)"
    check_str(name, value)
    if value in ("auto", "local"):
        return value
    match = RAY_ADDRESS.fullmatch(value)
    if match is None or not 1 <= int(match.group(3)) <= 65535:
        raise InvalidValue(name, value, expected)
    return value


TEMPLATE_FIELDS = ("env", "seed", "proposal")
"""The fields a ``reuse`` path template may hold, each plain (``{seed}``: no attribute, index, conversion or spec)."""


def _check_template(name: str, value: Any) -> str:
    check_str(name, value)
    expected = "a path template using only plain {env}, {seed} and {proposal} fields"
    try:
        fields = [(f, spec, conv) for _, f, spec, conv in Formatter().parse(value) if f is not None]
    except ValueError as e:
        raise InvalidValue(name, value, expected, note=f"ValueError: {e}") from None
    bad = [f"{{{f}{'!' + conv if conv else ''}{':' + spec if spec else ''}}}" for f, spec, conv in fields
           if f not in TEMPLATE_FIELDS or spec or conv]
    if bad:
        raise InvalidValue(name, value, expected, note=f"refused fields {bad}")
    return value


@dataclass
class ProtocolConfig:
    """Meta-test protocol (``umrl.evaluation.AdaptationConfig``): K steps, trajectories per task and step..."""

    num_steps: int = integer(min=1)
    num_trajectories: int = integer(min=1)
    horizon: int = integer(min=1)
    gamma: float = number(ge=0, le=1)
    lmbda: float = number(ge=0, le=1)
    normalize_advantage: bool = boolean()
    sgd_schedule: Any = checked(check_sgd_schedule)
    env_steps: int | None = integer(min=1)


@dataclass
class SweepConfig:
    enabled: bool = boolean()
    lrs: list[float] = number_list(min_len=1, gt=0)
    later_factors: list[float] = number_list(min_len=1, gt=0)
    num_tasks: int = integer(min=1)
    num_steps: int = integer(min=1)


@dataclass
class PretrainConfig:
    """One recipe's pre-training (``umrl.trainers.<name>.train``): ``reuse`` (finished runs used as they are: must hold a
    checkpoint) and ``overrides`` (recipe keys, checked against the recipe's schema)."""

    reuse: Any = checked(check_reuse)
    overrides: dict[str, Any] = mapping()


@dataclass
class MAMLPretrainConfig(PretrainConfig):
    """:class:`PretrainConfig` plus the maml recipe's key for the DIAYN run (``proposal=diayn``)."""

    diayn_checkpoint_key: str = string()


@dataclass
class PretrainGroup:
    diayn: PretrainConfig = field(default_factory=PretrainConfig)
    maml: MAMLPretrainConfig = field(default_factory=MAMLPretrainConfig)
    vime: PretrainConfig = field(default_factory=PretrainConfig)


@dataclass
class AblationConfig:
    """Meta-test of kept MAML checkpoints: ``methods`` must be MAML methods of the suite's ``methods``;
    ``baselines`` methods that are not meta-trained (scratch; one that needs pre-training must be in ``methods``),
    meta-tested once per seed at the ablation's K as the level every checkpoint is read against."""

    enabled: bool = boolean()
    methods: list[str] = choice_list(MAML_METHODS)
    baselines: list[str] = choice_list(BASELINE_METHODS)
    seeds: list[int] = int_list(min=0, max=SEED_MAX, unique=True)
    max_checkpoints: int = integer(min=1)
    num_steps: int = integer(min=1)


@dataclass
class LauncherConfig:
    """``workers`` (0: inline), torch ``threads`` per job, ``ray_address`` (null: local processes)."""

    workers: int = integer(min=0)
    threads: int = integer(min=1, max=MAX_THREADS)
    ray_address: str | None = checked(check_ray_address)


@dataclass
class ReportConfig:
    steps: list[int] = int_list(min=0, unique=True)


@dataclass
class SuiteConfig:
    """Every key of ``umrl/suite/config/suite.yaml`` (after a profile); the yaml's comments say what each does."""

    profile_name: str = name()  # a folder name under outputs/suite
    env_module: str | None = checked(import_env_module)  # before envs: the registry it reads may grow
    envs: list[str] = choice_list(ENV_NAMES, min_len=1)
    methods: list[str] = choice_list(METHODS, min_len=1)
    seeds: list[int] = int_list(min=0, max=SEED_MAX, min_len=1, unique=True)
    pretrain_seeds: Any = checked(check_pretrain_seeds)
    num_tasks: int = integer(min=1)
    protocol: ProtocolConfig = field(default_factory=ProtocolConfig)
    sgd_lr: float | None = number(gt=0)
    adam_lr: float = number(gt=0)
    sweep: SweepConfig = field(default_factory=SweepConfig)
    skill_trajectories: int = integer(min=1)
    pretrain: PretrainGroup = field(default_factory=PretrainGroup)
    ablation: AblationConfig = field(default_factory=AblationConfig)
    launcher: LauncherConfig = field(default_factory=LauncherConfig)
    report: ReportConfig = field(default_factory=ReportConfig)
    logger: LoggerConfig = field(default_factory=LoggerConfig)
    device: str = device()
    output_dir: str = writable_dir()

    @staticmethod
    def cross_check(cfg: dict) -> list[str]:
        """Ablation methods among ``methods``, overrides against the recipes' schemas (DIAYN's
        CUDA graphs and torch.compile against the suite's device), a meta-test batch that fits in memory
        (:func:`memory_errors`) and every ``reuse`` run the suite would use present."""
        errors = []
        pseeds = cfg["pretrain_seeds"]
        if isinstance(pseeds, list) and len(pseeds) != len(cfg["seeds"]):
            errors.append(InvalidValue("pretrain_seeds", pseeds, f"null, an integer >= 0 or a list of "
                                       f"{len(cfg['seeds'])} integers >= 0 (one per seed in {cfg['seeds']})").message())
        if cfg["ablation"]["enabled"]:
            missing = [m for m in cfg["ablation"]["methods"] if m not in cfg["methods"]]
            if missing:
                errors.append(InvalidValue("ablation.methods", cfg["ablation"]["methods"],
                                           f"methods also listed in methods ({', '.join(cfg['methods'])})",
                                           note=f"{missing} would be skipped").message())
            unplanned = [m for m in cfg["ablation"]["baselines"] if METHODS[m].pretraining and m not in cfg["methods"]]
            if unplanned:
                errors.append(InvalidValue("ablation.baselines", cfg["ablation"]["baselines"],
                                           "methods that need no pre-training (scratch) or are also listed in methods "
                                           f"({', '.join(cfg['methods'])})",
                                           note=f"{unplanned} would have no pre-training run").message())
        for recipe, schema in RECIPE_SCHEMAS.items():
            errors += check_partial(cfg["pretrain"][recipe]["overrides"], schema, f"pretrain.{recipe}.overrides.")
        diayn, maml = cfg["pretrain"]["diayn"]["overrides"], cfg["pretrain"]["maml"]["overrides"]
        if "device" not in diayn:  # the pre-training runs take the suite's device
            optim = diayn.get("optim") or {}
            errors += cudagraphs_errors(bool(optim.get("cudagraphs")), cfg["device"],
                                        "pretrain.diayn.overrides.optim.cudagraphs")
        if "device" not in maml:
            errors += cudagraphs_errors(bool(maml.get("cudagraphs")), cfg["device"], "pretrain.maml.overrides.cudagraphs")
        for run in needed_pretraining(cfg["methods"]):  # the MAML runs the suite trains take the overrides
            if run.recipe == "maml" and not _reuse_template(cfg, run):
                errors += num_skills_errors(run.proposal, maml.get("num_skills"), "pretrain.maml.overrides.num_skills")
        return errors + memory_errors(cfg) + _reuse_errors(cfg)

    @staticmethod
    def notices(cfg: dict) -> list[str]:
        """``report.steps`` above K (``protocol.num_steps``): the table has no column for them."""
        steps, k = cfg["report"]["steps"], cfg["protocol"]["num_steps"]
        beyond = [step for step in steps if step > k]
        return [InvalidValue("report.steps", steps, f"steps <= protocol.num_steps ({k}) to show each in the table",
                             note=f"{beyond} left out: K = protocol.num_steps = {k}").message()] if beyond else []


def memory_errors(cfg: Mapping) -> list[str]:
    """One meta-test cell's batch on the largest env of ``envs`` (``num_tasks`` x ``protocol.num_trajectories`` x
    ``protocol.horizon`` steps, or ``protocol.env_steps`` per task) against the memory of ``device``
    (:mod:`umrl.configs.memory`); cells running at once on several workers need that much each."""
    protocol, tasks = cfg["protocol"], cfg["num_tasks"]
    step, horizon = max(step_bytes(env) for env in cfg["envs"]), protocol["horizon"]
    if protocol["env_steps"] is None:
        batch = Allocation("protocol.num_trajectories", protocol["num_trajectories"], tasks * horizon * step,
                           f"meta-test batch: {tasks} tasks x {horizon} steps per trajectory",
                           f"with num_tasks={tasks} and protocol.horizon={horizon}")
    else:
        batch = Allocation("protocol.env_steps", protocol["env_steps"], tasks * step,
                           f"meta-test batch: {tasks} tasks", f"with num_tasks={tasks}")
    return allocation_errors([batch], cfg["device"])


def needed_pretraining(methods: list[str]) -> list[Pretraining]:
    """The pre-training runs the suite's ``methods`` use, with the runs they read (sorted by kind)."""
    runs = {METHODS[m].pretraining for m in methods} - {None}
    runs |= {r for run in runs for r in run.requires}
    return sorted(runs, key=lambda r: r.kind)


def pretrain_seeds(cfg: Mapping) -> list[int]:
    """The pre-training seed of each meta-test seed (``pretrain_seeds`` validated): null = the meta-test seeds
    (independent pre-training), an int = one run shared by every seed, or a list as long as ``seeds``."""
    value, seeds = cfg["pretrain_seeds"], [int(s) for s in cfg["seeds"]]
    if value is None:
        return seeds
    if isinstance(value, int):
        return [value] * len(seeds)
    return [int(v) for v in value]


def _reuse_template(cfg: Mapping, run: Pretraining) -> str | None:
    """The ``pretrain.<recipe>.reuse`` template for ``run`` (for MAML, a mapping's entry for its proposal), or None."""
    template = cfg["pretrain"][run.recipe]["reuse"]
    return template.get(run.proposal) if isinstance(template, Mapping) else template


def reuse_dir(cfg: Mapping, run: Pretraining, env: str, seed: int) -> Path | None:
    """The finished run ``pretrain.<recipe>.reuse`` names for ``run`` on (``env``, ``seed``), or None: a template with
    ``{env}``, ``{seed}``, ``{proposal}``, or for MAML a mapping from proposal to template."""
    template = _reuse_template(cfg, run)
    return Path(str(template).format(env=env, seed=seed, proposal=run.proposal)).absolute() if template else None


def _reuse_meta(run: Pretraining, run_dir: Path) -> dict:
    """The ``meta`` of the newest checkpoint in ``run_dir``, read with ``run``'s recipe's loader (a checkpoint of
    another recipe, a corrupted or an old pickle file raises ``ValueError`` naming it)."""
    loader = {"diayn": load_diayn_checkpoint, "maml": load_maml_checkpoint, "vime": load_vime_checkpoint}[run.recipe]
    return loader(run_dir)["meta"]


def _reuse_errors(cfg: dict) -> list[str]:
    """A ``reuse`` template the suite would use must point at runs holding a checkpoint for every (env, seed), of
    the method's recipe, env and (MAML) proposal; a reused UML-DIAYN run must have as many skills as the DIAYN run."""
    errors = []
    skills: dict[tuple[str, str, int], int] = {}
    for run in needed_pretraining(cfg["methods"]):
        template, key = cfg["pretrain"][run.recipe]["reuse"], f"pretrain.{run.recipe}.reuse"
        if isinstance(template, Mapping):
            template, key = template.get(run.proposal), f"{key}.{run.proposal}"
        for env in cfg["envs"]:
            for seed in sorted(set(pretrain_seeds(cfg))):
                run_dir = reuse_dir(cfg, run, env, seed)
                if run_dir is None:
                    continue
                if Checkpointer(run_dir / "checkpoints").latest() is None:
                    errors.append(InvalidValue(
                        key, template, "a finished run directory holding checkpoints/step_*.safetensors",
                        note=f"env={env} seed={seed}: {run_dir} has no checkpoint").message())
                    continue
                expected = {"env": env, **({"proposal": run.proposal} if run.proposal else {})}
                try:
                    meta = _reuse_meta(run, run_dir)
                except ValueError as e:
                    errors.append(InvalidValue(key, template, f"a {run.kind} run", note=str(e).splitlines()[0]).message())
                    continue
                found = {k: meta.get(k) for k in expected}
                if found != expected:
                    errors.append(InvalidValue(key, template, f"a {run.kind} run with {expected}",
                                               note=f"env={env} seed={seed}: {run_dir} holds {found}").message())
                elif run.kind in ("diayn", "maml_diayn"):
                    skills[run.kind, env, seed] = meta.get("num_skills")
    for (kind, env, seed), count in skills.items():
        diayn = skills.get(("diayn", env, seed))
        if kind == "maml_diayn" and diayn is not None and count != diayn:
            errors.append(InvalidValue("pretrain.maml.reuse", cfg["pretrain"]["maml"]["reuse"],
                                       f"a UML-DIAYN run on the reused DIAYN run's {diayn} skills",
                                       note=f"env={env} seed={seed}: it meta-trained on {count} skills").message())
    return errors
