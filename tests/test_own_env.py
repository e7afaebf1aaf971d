"""Your own env: a gymnasium id and a task family registered with gym_env_spec run every recipe, from Python and
from the command line (env.module); bad specs are refused before any work, naming what is wrong."""
import importlib
import math
import re
import subprocess
import sys

import pytest
import torch
from omegaconf import OmegaConf
from script_loading import REPO, load_script
from tensordict import TensorDict

from umrl.configs import ConfigError, validate
from umrl.configs.diayn import DIAYNConfig
from umrl.configs.validate import resume_diff
from umrl.envs import ENV_NAMES, TaskFamily, make_env, make_task_env, register_env, unregister_env
from umrl.envs.gym_cmp import gym_env_spec
from umrl.optim.meta_hvp import MetaHVP
from umrl.trainers import compose
from umrl.validation import InvalidType, InvalidValue

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def cart_reward(next_td, action, task):
    """InvertedPendulum: stay at cart position ``task``."""
    return -(next_td["qpos"][:, :1] - task).abs()


def pendulum_spec(**changes):
    """``gym:InvertedPendulum-v5`` (actions in [-3, 3]) with the applied control and the joint positions as physics
    keys, computed from the unwrapped env (its info is empty)."""
    family = TaskFamily("pendulum", 1, -0.5, 0.5, reward_fn=changes.pop("reward_fn", cart_reward),
                        sampler=changes.pop("sampler", None))
    physics = {"qpos": lambda env: env.data.qpos.copy(), "ctrl": lambda env: env.data.ctrl.copy()}
    return gym_env_spec(changes.pop("gym_id", "InvertedPendulum-v5"), family, changes.pop("physics", physics),
                        coverage_key="ctrl", coverage_reduction="mean", **changes)


@pytest.fixture
def pendulum():
    spec = register_env(pendulum_spec())
    yield spec
    unregister_env(spec.name)


def test_a_gym_env_becomes_a_reward_free_cmp_with_actions_in_unit_bounds(pendulum):
    assert pendulum.name == "gym:InvertedPendulum-v5" and (pendulum.obs_dim, pendulum.act_dim) == (4, 1)
    assert dict(pendulum.physics_keys) == {"qpos": 2, "ctrl": 1}
    env = make_env(pendulum.name, 2, seed=0, horizon=3)
    assert env.action_spec.space.low.tolist() == [[-1.0], [-1.0]] and env.action_spec.space.high.max() == 1.0
    td = env.reset()
    td["action"] = torch.tensor([[0.5], [2.0]])  # 2.0 is clipped to 1, then both are scaled to the env's [-3, 3]
    out = env.step(td)["next"]
    assert out["observation"].dtype == torch.float32 and out["observation"].shape == (2, 4)
    torch.testing.assert_close(out["ctrl"], torch.tensor([[1.5], [3.0]]))
    assert (out["reward"] == 0).all() and (out["env_reward"] == 1).all()  # gymnasium's reward kept aside
    tasks = torch.tensor([[0.25], [-0.25]])
    env = make_task_env(pendulum.name, tasks, seed=0, horizon=3)
    rollout = env.rollout(3)
    torch.testing.assert_close(rollout["next", "reward"], -(rollout["next", "qpos"][..., :1] - tasks[:, None]).abs())
    assert rollout["next", "done"][:, -1].all()  # the horizon ends the episodes


def test_an_env_observing_float32_works_as_one_observing_float64():
    """Classic control observes float32 (MuJoCo float64): both become float32 observations."""
    family = TaskFamily("swing", 1, -1.0, 1.0, reward_fn=lambda next_td, action, task: next_td["torque"] - task)
    spec = register_env(gym_env_spec("Pendulum-v1", family, {"torque": lambda env: [env.last_u or 0.0]},
                                     coverage_key="torque", coverage_reduction="mean"))
    try:
        rollout = make_env(spec.name, 2, seed=0, horizon=3).rollout(3)
        assert rollout["next", "observation"].dtype == torch.float32 and rollout["next", "observation"].shape == (2, 3, 3)
    finally:
        unregister_env(spec.name)


def test_held_out_tasks_come_from_the_family_sampler_seeded():
    def sampler(n, generator):
        return torch.randint(0, 3, (n, 1), generator=generator).float() / 4  # speeds 0, 0.25, 0.5
    spec = pendulum_spec(sampler=sampler)
    tasks = spec.eval_tasks()
    assert tasks.shape == (20, 1) and set(tasks[:, 0].tolist()) <= {0.0, 0.25, 0.5}
    torch.testing.assert_close(tasks, spec.eval_tasks())  # the same held-out set on every call


def wrong_width_reward(next_td, action, task):
    return -(next_td["qpos"][:, 0] - task[:, 0]).abs()  # [B], not [B, 1]


@pytest.mark.parametrize(("changes", "error", "message"), [
    ({"reward_fn": None}, InvalidType, r"task_family.reward_fn: got None; expected a function reward\(next_td"),
    ({"reward_fn": wrong_width_reward}, InvalidValue,
     r"task_family.reward_fn: got .* \(it returned a tensor of shape \[2\] .*\); expected .* \[B, 1\]"),
    ({"sampler": lambda n, g: torch.rand(n, 2, generator=g)}, InvalidValue,
     r"task_family.sampler: .*it returned a tensor of shape \[2, 2\]"),
    ({"sampler": lambda n, g: torch.rand(n, 1)}, InvalidValue, r"task_family.sampler: .*two draws with one seed differ"),
    ({"gym_id": "CartPole-v1"}, InvalidValue, r"action space of CartPole-v1: got Discrete\(2\).*continuous"),
    ({"gym_id": "InvertedPendulm-v5"}, InvalidValue,
     r"gym_id: got 'InvertedPendulm-v5' \(did you mean 'InvertedPendulum-v5'.*\); expected an id of gymnasium"),
    ({"physics": {"speed": "x_velocity"}}, InvalidValue,
     r"physics\['speed'\]: got \['x_velocity'\] \(\['x_velocity'\] not in its reset or step info\)"),
])
def test_bad_specs_are_refused_naming_the_key_the_value_and_what_is_accepted(changes, error, message):
    with pytest.raises(error, match=message):
        pendulum_spec(**changes)


def test_kl_hessian_share_of_batches_with_different_trajectory_counts():
    """sample_by=env_steps on an env whose episodes end early (Hopper falls over) gives support and query different
    numbers of trajectories per task: each share is drawn within its own count; equal counts share one draw."""
    hvp = MetaHVP(None, fraction=0.5, generator=torch.Generator().manual_seed(0))
    support, query = (TensorDict({"i": torch.arange(n).expand(2, n)}, [2, n]) for n in (4, 3))
    part_s, part_q = hvp.subsample(support, query)
    assert part_s.shape == (2, 2) and part_q.shape == (2, 2) and part_q["i"].max() < 3
    part_s, part_q = hvp.subsample(support, support.clone())
    assert torch.equal(part_s["i"], part_q["i"])


def diayn_config(*overrides):
    return compose("diayn", ["+profile=diayn_tiny", *overrides])


def test_config_imports_env_module_before_checking_env_name(tmp_path):
    module = tmp_path / "my_env.py"
    module.write_text(
        "from umrl.envs import TaskFamily, register_env\n"
        "from umrl.envs.gym_cmp import gym_env_spec\n\n"
        "def reward(next_td, action, task):\n"
        "    return -(next_td['ctrl'] - task).abs()\n\n"
        "register_env(gym_env_spec('InvertedPendulum-v5', TaskFamily('cart', 1, -1.0, 1.0, reward_fn=reward),\n"
        "                          physics={'ctrl': lambda env: env.data.ctrl.copy()}))\n")
    try:
        cfg = validate(diayn_config(f"env.module={module}", "env.name=gym:InvertedPendulum-v5",
                                    f"output_dir={tmp_path}/run"), DIAYNConfig)
        assert cfg.env.name in ENV_NAMES and cfg.env.horizon == 100  # umrl/configs/diayn_env/default.yaml's
    finally:
        unregister_env("gym:InvertedPendulum-v5")


@pytest.mark.parametrize(("overrides", "message"), [
    (["env.name=gym:Hopper-v5"], r"env.name: got 'gym:Hopper-v5' \(gymnasium has Hopper-v5, but no task family"),
    (["env.name=gym:Hoper-v5"], r"env.name: got 'gym:Hoper-v5' \(did you mean 'Hopper-v5'"),
    (["env.name=hopper"], r"env.name: got 'hopper'; expected one of 'point_nav', .* or gym:<EnvId>"),
    (["env.module=no_such_module_xyz"], r"env.module: got 'no_such_module_xyz' \(importing it raised ModuleNot"),
    (["env.module=missing/my_env.py"], r"env.module: got 'missing/my_env.py' \(.* is not a file\)"),
])
def test_bad_env_names_and_modules_get_one_clear_line(tmp_path, overrides, message):
    with pytest.raises(ConfigError) as raised:
        validate(diayn_config(*overrides, f"output_dir={tmp_path}"), DIAYNConfig)
    assert any(re.match(message, line) for line in raised.value.errors), raised.value.errors


def test_runs_saved_before_env_module_existed_resume():
    cfg = compose("maml", ["+profile=maml_tiny"])
    saved = OmegaConf.to_container(cfg, resolve=True)
    del saved["env"]["module"]
    assert resume_diff(saved, cfg) == {}
    assert resume_diff(saved, compose("maml", ["+profile=maml_tiny", "env.module=my_pkg.my_env"])) == {
        "env.module": ("<absent>", "my_pkg.my_env")}


def test_several_seeds_on_a_gym_env_are_refused(tmp_path, pendulum):
    with pytest.raises(ConfigError, match=r"seeds: got \[0, 1\] \(the seeds would share one gymnasium vector env"):
        validate(diayn_config(f"env.name={pendulum.name}", "seeds=[0,1]", f"output_dir={tmp_path}"), DIAYNConfig)


@pytest.mark.slow
def test_own_env_example_runs_diayn_uml_and_meta_test_beside_scratch(tmp_path):
    example = load_script("examples/own_env.py")
    returns = example.own_env(str(tmp_path), steps=1, num_tasks=2, trajectories=2, horizon=20,
                              diayn=["collector.total_frames=160", "collector.init_random_frames=80",
                                     "collector.frames_per_batch=80", "eval.every=160", "checkpoint.every=160",
                                     "eval.episodes_per_skill=1", "env.horizon=20", "logger.backend=none"],
                              maml=["iterations=1", "meta_batch_size=2", "logger.backend=none"])
    assert sorted(returns) == ["scratch", "uml_diayn"]
    assert all(len(curve) == 2 and all(map(math.isfinite, curve)) for curve in returns.values())  # k = 0 and 1
    assert (tmp_path / "maml" / "checkpoints" / "step_1.safetensors").is_file()


@pytest.mark.slow
def test_command_lines_train_diayn_then_maml_on_an_env_module(tmp_path):
    """The recipes import env.module before checking env.name (one subprocess per recipe)."""
    common = ["env.module=examples/own_env.py", "env.name=gym:Hopper-v5", "logger.backend=none", "progress=false",
              "env.horizon=20"]
    diayn = ["+profile=diayn_tiny", "collector.total_frames=160", "collector.init_random_frames=80",
             "collector.frames_per_batch=80", "eval.every=160", "checkpoint.every=160", "eval.episodes_per_skill=1",
             f"output_dir={tmp_path}/diayn"]
    maml = ["+profile=maml_tiny", "proposal=diayn", f"diayn_checkpoint={tmp_path}/diayn", "iterations=1",
            "meta_batch_size=2", "trajectories_per_task=2", f"output_dir={tmp_path}/maml"]
    for recipe, overrides in (("diayn", diayn), ("maml", maml)):
        proc = subprocess.run([sys.executable, str(REPO / "recipes" / f"{recipe}.py"), *common, *overrides],
                              cwd=REPO, check=False, capture_output=True, text=True, timeout=300)
        assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "maml" / "checkpoints" / "step_1.safetensors").is_file()


@pytest.mark.parametrize("recipe", ["diayn", "maml"])
def test_resume_on_a_gym_env_is_bit_identical(tmp_path, pendulum, recipe):
    """The vector env's reset noise is part of the checkpoint: a resumed run ends where an uninterrupted one does
    (the pendulum falls within a few steps, so the runs reset copies throughout)."""
    from test_resume import BUDGET, checkpoint_diffs, config

    from umrl.checkpoints.file import read_checkpoint

    train = importlib.import_module(f"umrl.trainers.{recipe}").train
    key, stop, end = BUDGET[recipe]
    whole = train(config(recipe, tmp_path / "whole", pendulum.name, f"{key}={end}"))
    train(config(recipe, tmp_path / "split", pendulum.name, f"{key}={stop}"))
    resumed = train(config(recipe, tmp_path / "split", pendulum.name, f"{key}={end}", "resume=true"))
    diffs = checkpoint_diffs(read_checkpoint(whole["checkpoint"]), read_checkpoint(resumed["checkpoint"]))
    assert {path: d for path, d in diffs.items() if d != 0} == {}
    assert any("reset_rngs" in path for path in diffs)


def test_diayn_on_a_gym_env_restarts_episodes_at_checkpoints_and_keeps_the_schedule(tmp_path, pendulum):
    """gymnasium's vector env cannot give its copies' physics state: DIAYN restarts the episodes at every checkpoint
    there (a resumed run restarts them too, so resuming stays exact), and a resume with another ``checkpoint.every``
    is refused."""
    from test_resume import BUDGET, config

    from umrl.checkpoints.file import read_checkpoint
    from umrl.trainers.diayn import train

    key, stop, _ = BUDGET["diayn"]
    result = train(config("diayn", tmp_path, pendulum.name, f"{key}={stop}"))
    assert "episodes" not in read_checkpoint(result["checkpoint"])
    with pytest.raises(ConfigError, match="checkpoint.every: checkpoint has 40, this run has 80"):
        train(config("diayn", tmp_path, pendulum.name, f"{key}={stop * 2}", "checkpoint.every=80", "resume=true"))
