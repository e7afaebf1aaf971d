"""The replay buffer of S seeds trained side by side, each sampled from its own data with its own generator.

The seeds step in lockstep (one env step of every seed's copies at a time), so their transitions are stored as rows of
``S`` in one TensorDict ring ``[capacity, S]`` (column ``s``: seed ``s``'s transitions): every seed always holds the
same number of transitions. :meth:`SeedReplay.sample` draws each seed's row indices from that seed's generator,
gathers column ``s`` only, and adds the standard normal action noise
:class:`~umrl.objectives.stacked_diayn.StackedDIAYNLoss` reads, from the same generator: seed ``s``'s sample never
depends on the other seeds.

Why not TorchRL's ``ReplayBuffer``: the reference schedule writes one transition per seed per env step, and
``TensorDictReplayBuffer.extend`` costs about 0.7 ms a call on a 2-core CPU (measured with cProfile in the DIAYN
loop: its writer, locks and TensorDict indexing), more than the MuJoCo step itself; its samplers also draw one index
set for the whole buffer, not one per seed. Here a write is one in-place copy per key.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDict, TensorDictBase

__all__ = ["SeedReplay"]


class SeedReplay:
    """Replay of ``len(generators)`` seeds (see the module docstring).

    Args:
        capacity: rows kept (each row one transition per seed); the oldest are overwritten.
        batch_size: transitions sampled per seed.
        generators: one torch generator per seed, on ``device``.
        act_dim: width of the action noise.
        device: storage device.

    :meth:`extend` takes transitions ``[N, S]``; :meth:`sample` returns ``[S, batch_size]`` with ``"action_noise"``
    and ``("next", "action_noise")`` ``[S, batch_size, act_dim]``; :meth:`state_dict` holds the filled rows in
    write order and the write position (the generators are saved by their owner).

    Examples:
        >>> from tensordict import TensorDict
        >>> gens = [torch.Generator().manual_seed(s) for s in (0, 1)]
        >>> replay = SeedReplay(100, batch_size=4, generators=gens, act_dim=2)
        >>> replay.extend(TensorDict({"observation": torch.arange(20.).view(10, 2, 1)}, [10, 2]))
        >>> batch = replay.sample()
        >>> batch.shape, batch["action_noise"].shape
        (torch.Size([2, 4]), torch.Size([2, 4, 2]))
        >>> bool((batch["observation"][1] % 2 == 1).all())  # seed 1's column only
        True
    """

    def __init__(self, capacity: int, *, batch_size: int, generators: Sequence[torch.Generator], act_dim: int,
                 device: torch.device | str = "cpu"):
        self.capacity, self.batch_size, self.act_dim = capacity, batch_size, act_dim
        self.generators, self.device = list(generators), torch.device(device)
        self.storage: TensorDictBase | None = None  # [capacity, S], allocated at the first write
        self._leaves: list[tuple[tuple, torch.Tensor]] = []
        self.cursor, self.size = 0, 0
        self._columns = torch.arange(len(self.generators), device=self.device).unsqueeze(-1)

    def __len__(self) -> int:
        """Transitions held per seed."""
        return self.size

    def _allocate(self, like: TensorDictBase) -> None:
        self.storage = like.apply(
            lambda t: torch.empty((self.capacity, *t.shape[1:]), dtype=t.dtype, device=self.device),
            batch_size=[self.capacity, *like.shape[1:]], device=self.device)
        self._leaves = [(key, self.storage.get(key)) for key in self.storage.keys(True, True)]

    def extend(self, data: TensorDictBase) -> None:
        """Append transitions ``[N, S]`` (row ``i``: the i-th transition of every seed), overwriting the oldest."""
        if data.batch_dims != 2 or data.shape[1] != len(self.generators):
            raise ValueError(f"expected transitions [N, {len(self.generators)}] (one column per seed), got "
                             f"batch {tuple(data.shape)}.")
        if self.storage is None:
            self._allocate(data)
        count = data.shape[0]
        if count > self.capacity:
            raise ValueError(f"cannot write {count} rows into a replay of {self.capacity}.")
        end = self.cursor + count
        if end <= self.capacity:
            for key, leaf in self._leaves:
                leaf[self.cursor:end] = data.get(key)
        else:
            rows = torch.arange(self.cursor, end, device=self.device) % self.capacity
            for key, leaf in self._leaves:
                leaf[rows] = data.get(key)
        self.cursor = end % self.capacity
        self.size = min(self.size + count, self.capacity)

    def draw(self, shape: Sequence[int], kind: str) -> torch.Tensor:
        """``[S, *shape]`` from every seed's generator: ``kind`` ``"normal"`` (standard normal) or ``"uniform"``
        (on [-1, 1))."""
        if kind == "normal":
            return torch.stack([torch.randn(*shape, generator=g, device=self.device) for g in self.generators])
        return torch.stack([torch.rand(*shape, generator=g, device=self.device) for g in self.generators]) * 2 - 1

    def sample(self) -> TensorDictBase:
        """``batch_size`` transitions of every seed, uniformly from its own column, with fresh action noise."""
        if self.size == 0:
            raise RuntimeError("SeedReplay.sample: the buffer is empty.")
        rows = torch.stack([torch.randint(self.size, (self.batch_size,), generator=g, device=self.device)
                            for g in self.generators])  # [S, batch_size]
        # one index_select per key on the storage viewed as [capacity * S]: less work than TensorDict's indexing
        index = (rows * len(self.generators) + self._columns).view(-1)
        batch = {key: leaf.flatten(0, 1).index_select(0, index).view(*rows.shape, *leaf.shape[2:])
                 for key, leaf in self._leaves}
        batch["next", "action_noise"] = self.draw((self.batch_size, self.act_dim), "normal")
        batch["action_noise"] = self.draw((self.batch_size, self.act_dim), "normal")
        return TensorDict(batch, batch_size=rows.shape, device=self.device)

    def state_dict(self) -> dict:
        """The filled rows (a clone, oldest first), for :meth:`load_state_dict`."""
        if self.storage is None:
            return {"rows": None, "cursor": 0, "size": 0}
        order = (torch.arange(self.size, device=self.device) + (self.cursor - self.size)) % self.capacity
        return {"rows": self.storage[order].clone(), "cursor": self.cursor, "size": self.size}

    def load_state_dict(self, state: dict) -> None:
        """Restore what :meth:`state_dict` took into a replay built the same way (same capacity and seeds)."""
        rows, cursor, size = state["rows"], int(state["cursor"]), int(state["size"])
        if rows is None:
            return
        if rows.shape[0] != size or size > self.capacity or not 0 <= cursor < max(self.capacity, 1):
            raise ValueError(f"replay state of {rows.shape[0]} rows (size {size}, cursor {cursor}) does not fit a "
                             f"replay of {self.capacity}.")
        self._allocate(rows)
        self.cursor = (cursor - size) % self.capacity
        self.size = 0
        self.extend(rows.to(self.device))
