"""Seeding (:mod:`umrl.rng`) and the replay-buffer state a resume restores (:mod:`umrl.resume_state`)."""
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
