"""Seeding (:mod:`umrl.rng`), and the replay-buffer and env states a resume restores (:mod:`umrl.resume_state`): the
envs' episodes in progress continue bit for bit."""
import pytest
import torch

from umrl.rng import seed_everything


def test_seed_everything_reproduces_draws():
    seed_everything(7)
    a = torch.rand(3)
    seed_everything(7)
    assert torch.equal(a, torch.rand(3))


def test_replay_buffer_state_keeps_only_filled_rows_and_round_trips_through_wraps():
    from tensordict import TensorDict
    from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

    from umrl.resume_state import load_replay_buffer_state, replay_buffer_state

    def make():
        return TensorDictReplayBuffer(storage=LazyTensorStorage(7), batch_size=2)

    def rows(start, n):
        return TensorDict({"x": torch.arange(start, start + n, dtype=torch.float32)}, [n])

    buffer = make()
    buffer.extend(rows(0, 3))
    state = replay_buffer_state(buffer)
    assert state["_storage"]["rows"]["x"].tolist() == [0, 1, 2]  # not the 7 allocated rows
    assert state["_storage"]["rows"]["x"].untyped_storage().nbytes() == 3 * 4  # a copy, not a view of them
    buffer.extend(rows(10, 6))  # wraps: the write cursor passes the end
    restored = make()
    load_replay_buffer_state(restored, replay_buffer_state(buffer))
    for b in (buffer, restored):
        b.extend(rows(100, 2))
    assert restored.storage[:7]["x"].tolist() == buffer.storage[:7]["x"].tolist()
    assert len(restored) == len(buffer) == 7


def _steps(env, td, steps: int, generator):
    """``steps`` env steps with uniform actions from ``generator``: (their outputs stacked, the last carry)."""
    outputs = []
    for _ in range(steps):
        td.set("action", torch.rand(td.batch_size + env.action_spec.shape[-1:], generator=generator) * 2 - 1)
        out, td = env.step_and_maybe_reset(td)
        outputs.append(out)
    return torch.stack(outputs), td


@pytest.mark.parametrize("name", ["point_nav", "half_cheetah", "ant"])
def test_env_state_with_episodes_continues_them_bit_for_bit(name):
    """``env_state(env, episodes=True)`` taken mid-episode and loaded into a fresh env (seeded otherwise, reset):
    with the saved carry, the next steps, through resets at the horizon, equal the saved env's."""
    from umrl.envs import make_env
    from umrl.resume_state import env_state, keeps_episodes, load_env_state

    env, generator = make_env(name, 4, seed=0, horizon=7), torch.Generator().manual_seed(1)
    assert keeps_episodes(env)
    _, carry = _steps(env, env.reset(), 5, generator)
    saved, saved_carry, draws = env_state(env, episodes=True), carry.clone(), generator.get_state()
    expected, _ = _steps(env, carry, 12, generator)
    fresh = make_env(name, 4, seed=3, horizon=7)
    fresh.reset()
    assert load_env_state(fresh, saved)
    generator.set_state(draws)
    continued, _ = _steps(fresh, saved_carry, 12, generator)
    assert [key for key in expected.keys(True, True) if not torch.equal(expected[key], continued[key])] == []
    assert expected["next", "done"].any()  # the comparison crossed episode ends (reset noise included)

    without = env_state(env)
    assert "episodes" not in without["base_env"] and not load_env_state(fresh, without)
    wrong = {**saved, "base_env": {**saved["base_env"], "episodes": env_state(make_env(name, 2), episodes=True)[
        "base_env"]["episodes"]}}
    with pytest.raises(ValueError, match=f"episode state '.*' of a {name} env of 4 copies must have shape"):
        load_env_state(fresh, wrong)


def test_gymnasium_envs_give_no_episodes():
    """gymnasium's vector env has no ``episode_state``: its env state holds none, and the trainers restart its
    episodes instead."""
    from umrl.envs import make_env
    from umrl.resume_state import env_state, keeps_episodes

    env = make_env("half_cheetah", 2, seed=0, backend="gym")
    assert not keeps_episodes(env)
    assert set(env_state(env, episodes=True)["base_env"]) == {"env"}
