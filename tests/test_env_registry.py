"""The env registry: one EnvSpec per env is all umrl reads; a toy env added through it alone runs every recipe."""
import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

import umrl.trainers
import umrl.trainers.vime
from umrl.envs import ENV_NAMES, EnvSpec, TaskFamily, get_env_spec, make_env, register_env, unregister_env
from umrl.trainers import compose

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


class LineEnv(EnvBase):
    """A batch of points on a line: ``x += 0.05 * clip(a)``; ``"observation"`` = ``"x"`` ``[B, 1]``, no reward."""

    batch_locked = True

    def __init__(self, num_envs, *, seed=None, device="cpu", backend="default"):
        super().__init__(device=device, batch_size=torch.Size([num_envs]))
        shape = (num_envs,)
        self.observation_spec = Composite(observation=Unbounded(shape + (1,)), x=Unbounded(shape + (1,)), shape=shape)
        self.action_spec = Bounded(-1.0, 1.0, shape + (1,))
        self.reward_spec = Unbounded(shape + (1,))
        self.done_spec = Composite({k: Categorical(2, shape + (1,), dtype=torch.bool)
                                    for k in ("done", "terminated", "truncated")}, shape=shape)
        self._x = torch.zeros(shape + (1,))

    def _out(self, **extra) -> TensorDict:
        false = torch.zeros_like(self._x, dtype=torch.bool)
        return TensorDict({"observation": self._x.clone(), "x": self._x.clone(), "done": false,
                           "terminated": false.clone(), "truncated": false.clone(), **extra}, self.batch_size)

    def _reset(self, tensordict: TensorDictBase | None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        self._x = torch.zeros_like(self._x) if mask is None else self._x.masked_fill(mask.reshape(-1, 1), 0.0)
        return self._out()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        self._x = self._x + 0.05 * tensordict["action"].clamp(-1, 1)
        return self._out(reward=torch.zeros_like(self._x))

    def _set_seed(self, seed):
        return None


def line_reward(next_td, action, task):
    return -(next_td["x"] - task).abs()


LINE = EnvSpec(name="line", make=LineEnv, obs_dim=1, act_dim=1,
               task_family=TaskFamily("line", task_dim=1, low=-1.0, high=1.0, reward_fn=line_reward),
               physics_keys={"x": 1}, coverage_key="x", horizon=10, num_eval_tasks=4)


@pytest.fixture
def line_env():
    register_env(LINE)
    yield LINE
    unregister_env("line")


@pytest.mark.parametrize("name", ["point_nav", "half_cheetah", "ant"])
def test_builtin_records_match_their_envs(name):
    spec = get_env_spec(name)
    env = make_env(name, 2, seed=0, horizon=3)
    assert env.observation_spec["observation"].shape == (2, spec.obs_dim)
    assert env.action_spec.shape == (2, spec.act_dim)
    rollout = env.rollout(3)
    for key, width in spec.physics_keys.items():
        assert rollout["next", key].shape == (2, 3, width), key
    assert spec.task_family.eval_tasks(spec.num_eval_tasks).shape[0] == 20
    env.close()


def test_bad_records_and_names_are_rejected():
    with pytest.raises(ValueError, match="already registered"):
        register_env(get_env_spec("point_nav"))
    with pytest.raises(ValueError, match="unknown env 'nowhere'; valid choices"):
        get_env_spec("nowhere")
    with pytest.raises(ValueError, match=r"unknown env 'ant_maml_reward'; valid choices: \['point_nav', "
                                         r"'half_cheetah', 'ant'"):
        get_env_spec("ant_maml_reward")  # removed: ant carries the MAML code's reward
    with pytest.raises(ValueError, match="coverage_key 'y'"):
        EnvSpec(**{**LINE.__dict__, "coverage_key": "y"})
    with pytest.raises(ValueError, match="obs_dim"):
        EnvSpec(**{**LINE.__dict__, "obs_dim": 0})
    with pytest.raises(ValueError, match="coverage_cell"):
        EnvSpec(**{**LINE.__dict__, "coverage_cell": 0.1})


def test_a_registered_env_runs_every_recipe(tmp_path, line_env):
    assert "line" in ENV_NAMES
    common = ["logger.backend=none", "progress=false", "env.name=line", "env.horizon=10"]
    result = umrl.trainers.train("maml", [
        *common, f"output_dir={tmp_path / 'maml'}", "proposal=oracle", "iterations=1", "trajectories_per_task=3",
        "policy.hidden=[8]", "trpo.cg_iters=2"])
    assert result["iteration"] == 1 and result["train/return_pre"] < 0  # -|x - g| summed over 10 steps

    result = umrl.trainers.train("diayn", [
        *common, f"output_dir={tmp_path / 'diayn'}", "env.num_envs=3", "collector.frames_per_batch=30",
        "collector.total_frames=60", "collector.init_random_frames=30", "optim.updates_per_frame=0.1",
        "network.hidden=[8]", "network.discriminator_hidden=[8]", "replay_buffer.batch_size=8", "eval.every=60",
        "eval.episodes_per_skill=2", "checkpoint.every=60"])
    assert 0.0 <= result["eval/final_state_accuracy"] <= 1.0 and "eval/centroid_range" in result  # 1-D coverage
    assert (tmp_path / "diayn" / "seed0" / "figures" / "skill_coverage.png").is_file()

    result = umrl.trainers.vime.train(compose("vime", [
        *common, f"output_dir={tmp_path / 'vime'}", "iterations=1", "env.num_envs=3", "policy.hidden=[8]",
        "dynamics.updates_per_iteration=2", "dynamics.batch_size=4"]))
    assert result["coverage/velocity_range"] >= 0 and result["train/frames"] == 30
