"""The replay buffer of S seeds trained side by side, each sampled from its own data with its own generator.

The seeds step in lockstep (one env step of every seed's copies at a time), so their transitions are stored as rows of
``S`` (TorchRL's :class:`~torchrl.data.LazyTensorStorage`, rows ``[S]``: column ``s`` is seed ``s``'s transition):
every seed always holds the same number of transitions. :meth:`SeedReplay.sample` draws each seed's row indices from
that seed's generator, gathers column ``s`` only, and adds the standard normal action noise
:class:`~umrl.objectives.stacked_diayn.StackedDIAYNLoss` reads, from the same generator: seed ``s``'s sample never
depends on the other seeds.
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
from tensordict import TensorDictBase
from torchrl.data import LazyTensorStorage, TensorDictReplayBuffer

__all__ = ["SeedReplay"]


class SeedReplay:
    """Replay of ``len(generators)`` seeds (see the module docstring).

    Args:
        capacity: rows kept (each row one transition per seed); the oldest are overwritten.
        batch_size: transitions sampled per seed.
        generators: one torch generator per seed, on ``device``.
        act_dim: width of the action noise.
        device: storage device.

    :attr:`buffer` is the TorchRL replay buffer (its ``state_dict`` and :func:`umrl.runtime.replay_buffer_state`
    save it); :meth:`extend` takes transitions ``[N, S]``; :meth:`sample` returns ``[S, batch_size]`` with
    ``"action_noise"`` and ``("next", "action_noise")`` ``[S, batch_size, act_dim]``.

    Examples:
        >>> from tensordict import TensorDict
        >>> gens = [torch.Generator().manual_seed(s) for s in (0, 1)]
        >>> replay = SeedReplay(100, batch_size=4, generators=gens, act_dim=2)
        >>> replay.extend(TensorDict({"observation": torch.arange(20.).view(10, 2, 1), "next": {}}, [10, 2]))
        >>> batch = replay.sample()
        >>> batch.shape, batch["action_noise"].shape
        (torch.Size([2, 4]), torch.Size([2, 4, 2]))
        >>> bool((batch["observation"][1] % 2 == 1).all())  # seed 1's column only
        True
    """

    def __init__(self, capacity: int, *, batch_size: int, generators: Sequence[torch.Generator], act_dim: int,
                 device: torch.device | str = "cpu"):
        self.buffer = TensorDictReplayBuffer(storage=LazyTensorStorage(capacity, device=device))
        self.batch_size, self.generators, self.act_dim = batch_size, list(generators), act_dim
        self.device = torch.device(device)
        self._columns = torch.arange(len(self.generators), device=self.device).unsqueeze(-1)

    def __len__(self) -> int:
        """Transitions held per seed."""
        return len(self.buffer)

    def extend(self, data: TensorDictBase) -> None:
        """Append transitions ``[N, S]`` (row ``i``: the i-th transition of every seed)."""
        if data.batch_dims != 2 or data.shape[1] != len(self.generators):
            raise ValueError(f"expected transitions [N, {len(self.generators)}] (one column per seed), got "
                             f"batch {tuple(data.shape)}.")
        self.buffer.extend(data)

    def draw(self, shape: Sequence[int], kind: str) -> torch.Tensor:
        """``[S, *shape]`` from every seed's generator: ``kind`` ``"normal"`` (standard normal) or ``"uniform"``
        (on [-1, 1))."""
        if kind == "normal":
            return torch.stack([torch.randn(*shape, generator=g, device=self.device) for g in self.generators])
        return torch.stack([torch.rand(*shape, generator=g, device=self.device) for g in self.generators]) * 2 - 1

    def sample(self) -> TensorDictBase:
        """``batch_size`` transitions of every seed, uniformly from its own column, with fresh action noise."""
        size = len(self.buffer)
        if size == 0:
            raise RuntimeError("SeedReplay.sample: the buffer is empty.")
        rows = torch.stack([torch.randint(size, (self.batch_size,), generator=g, device=self.device)
                            for g in self.generators])
        batch = self.buffer.storage[rows, self._columns.expand_as(rows)]
        batch.set(("next", "action_noise"), self.draw((self.batch_size, self.act_dim), "normal"))
        batch.set("action_noise", self.draw((self.batch_size, self.act_dim), "normal"))
        return batch
