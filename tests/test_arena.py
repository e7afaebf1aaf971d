"""The bounded-arena ablation of UML-random: point_nav's ``arena`` option, the ``random_arena`` proposal,
the ``env.arena`` config key and the ``uml_random_arena`` method end to end in a tiny suite."""
import math

import pytest
import torch
from script_loading import compose_config

from umrl import suite
from umrl.checkpoints import load_maml_checkpoint
from umrl.configs import ConfigError, validate
from umrl.configs.maml import MAMLConfig
from umrl.envs import make_env
from umrl.envs.point_nav import ACTION_SCALE, PointNavEnv
from umrl.metatest import METHODS, read_rows
from umrl.proposals import RANDOM_ARENA, make_proposal
from umrl.trainers import compose


def _positions(env, actions: torch.Tensor) -> torch.Tensor:
    """Positions ``[steps, B, 2]`` after each of ``actions`` ``[steps, B, 2]`` from a reset."""
    td = env.reset()
    out = []
    for action in actions:
        td = env.step(td.set("action", action))["next"]
        out.append(td["position"])
    return torch.stack(out)


def test_arena_clips_every_position():
    arena = 0.25
    env = make_env("point_nav", 3, arena=arena)
    actions = torch.stack([torch.tensor([[1.0, -1.0], [3.0, 0.5], [-2.0, 0.0]])] * 10)
    positions = _positions(env, actions)
    assert positions.abs().max() == arena  # the bound is reached and never passed
    assert torch.equal(positions[-1], torch.tensor([[arena, -arena], [arena, arena], [-arena, 0.0]]))
    random = _positions(env, 3 * torch.randn(50, 3, 2, generator=torch.Generator().manual_seed(0)))
    assert random.abs().max() <= arena
    # back from the wall at once: clipping keeps no hidden overshoot
    back = _positions(env, torch.cat([torch.ones(5, 3, 2), -torch.ones(1, 3, 2)]))
    assert torch.allclose(back[-1], torch.full((3, 2), arena - ACTION_SCALE))


def test_no_arena_is_the_unbounded_env_bit_for_bit():
    actions = 0.5 + 2 * torch.randn(40, 4, 2, generator=torch.Generator().manual_seed(1))  # drifts outwards
    default, explicit = make_env("point_nav", 4), make_env("point_nav", 4, arena=None)
    expected, reference = torch.zeros(4, 2), []
    for action in actions:  # the documented dynamics, written out
        expected = expected + ACTION_SCALE * action.clamp(-1.0, 1.0)
        reference.append(expected)
    positions = _positions(default, actions)
    assert torch.equal(positions, torch.stack(reference)) and torch.equal(positions, _positions(explicit, actions))
    assert positions.abs().max() > 1.0  # unbounded: the walk left the square an arena of 1 would impose
    assert default.observation_spec == explicit.observation_spec and default.base_env.arena is None


@pytest.mark.parametrize("arena", [0, -1.0, math.nan, True, "1"])
def test_bad_arena_is_refused(arena):
    with pytest.raises((ValueError, TypeError), match=r"arena: got .*; expected a finite number > 0"):
        PointNavEnv(2, arena=arena)


def test_envs_without_the_option_refuse_it():
    with pytest.raises(ValueError, match=r"half_cheetah.*\['arena'\].*accepts none"):
        make_env("half_cheetah", 1, arena=1.0)
    with pytest.raises(ValueError, match=r"\['wall'\].*accepts \['arena'\]"):
        make_env("point_nav", 1, wall=1.0)


def test_random_arena_proposal_is_random_in_a_bounded_arena():
    kwargs = {"num_tasks": 2, "trajectories_per_task": 2, "seed": 3, "num_skills": 4, "horizon": 10,
              "discriminator_hidden": [8]}
    plain, arena = make_proposal("random", "point_nav", **kwargs), make_proposal("random_arena", "point_nav", **kwargs)
    assert plain.env.base_env.arena is None and arena.env.base_env.arena == RANDOM_ARENA
    discriminators = [p.env.transform[-1] for p in (plain, arena)]
    for a, b in zip(*(d.parameters() for d in discriminators), strict=True):
        assert torch.equal(a, b)  # the same frozen random discriminator: only the arena differs
    assert make_proposal("random_arena", "point_nav", arena=0.5, **kwargs).env.base_env.arena == 0.5
    assert make_proposal("oracle", "point_nav", arena=0.5, **kwargs).env.base_env.arena == 0.5


@pytest.mark.parametrize("value", ["0", "-1", "abc"])
def test_maml_config_checks_env_arena(value):
    with pytest.raises(ConfigError, match="env.arena"):
        validate(compose("maml", [f"env.arena={value}"]), MAMLConfig)
    assert validate(compose("maml", ["env.arena=2"]), MAMLConfig).env.arena == 2


def test_uml_random_arena_runs_end_to_end_in_a_tiny_suite(tmp_path):
    assert METHODS["uml_random_arena"].pretraining.kind == "maml_random_arena"
    default_methods = compose_config("umrl/suite/config", "suite", []).methods
    assert "uml_random_arena" not in default_methods  # an ablation: asked for by name only
    maml = {"iterations": 1, "meta_batch_size": 2, "trajectories_per_task": 2, "num_skills": 4, "env.horizon": 10,
            "policy.hidden": "[16]", "trpo.cg_iters": 2, "checkpoint.every": 1}
    cfg = compose_config("umrl/suite/config", "suite", [
        f"output_dir={tmp_path}", "methods=[uml_random_arena]", "seeds=[0]", "pretrain_seeds=0", "num_tasks=2",
        "protocol.num_steps=1", "protocol.num_trajectories=2", "protocol.horizon=10", "report.steps=[0]",
        "logger.backend=none", "ablation.enabled=false", "launcher.threads=1", "launcher.workers=0",
        *(f"++pretrain.maml.overrides.{k}={v}" for k, v in maml.items())])
    suite.run_suite(cfg, log=lambda _: None)
    runs = list((tmp_path / "pretrain" / "maml_random_arena" / "point_nav").iterdir())
    assert len(runs) == 1
    state = load_maml_checkpoint(runs[0])
    assert state["meta"]["proposal"] == "random_arena" and state["iteration"] == 1
    rows = read_rows([tmp_path / "results.csv"])
    assert {r["method"] for r in rows} == {"uml_random_arena"} and len(rows) == 2 * 2  # 2 tasks x k = 0, 1
    assert all(math.isfinite(r["return"]) for r in rows)
