"""Finite deterministic controlled Markov processes (CMPs: an MDP without a reward) with a horizon.

A :class:`DeterministicCMP` is a successor table ``next_state[s, a]`` (``[S, A]`` integers), a start state and a
horizon ``T``: an episode takes ``T`` actions from the start state, so it visits ``s_0, ..., s_T``. The analysis of
goal reaching and trajectory matching (deterministic dynamics, finite horizon, undiscounted) is about this object.

Four families are built in: :func:`chain`, :func:`grid` (walls allowed), :func:`tree` and :func:`random_cmp`.

>>> cmp = chain(5, horizon=2)
>>> cmp.num_states, cmp.num_actions
(5, 3)
>>> reachable_at(cmp).nonzero().flatten().tolist()
[0, 1, 2]
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from umrl.validation import InvalidValue, check_int

#: grid actions, as (row, column) displacements: stay, up, down, left, right
GRID_MOVES = ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1))


@dataclass(frozen=True)
class DeterministicCMP:
    """A deterministic CMP: ``next_state`` ``[S, A]`` (long), ``start`` state, ``horizon`` T >= 1.

    ``shape`` (rows, columns) is set for grids, so that a vector over states can be drawn as an image
    (state ``s`` at row ``s // columns``, column ``s % columns``); ``name`` labels tables and figures.
    """

    next_state: torch.Tensor
    start: int
    horizon: int
    name: str = "cmp"
    shape: tuple[int, int] | None = None

    def __post_init__(self):
        table = self.next_state
        if not isinstance(table, torch.Tensor) or table.dim() != 2 or table.dtype != torch.long or table.numel() == 0:
            raise InvalidValue("next_state", table, "a non-empty [S, A] tensor of dtype torch.long")
        if table.min() < 0 or table.max() >= table.shape[0]:
            raise InvalidValue("next_state", table, f"successor indices in [0, {table.shape[0] - 1}]")
        check_int("start", self.start, min=0, max=table.shape[0] - 1)
        check_int("horizon", self.horizon, min=1)

    @property
    def num_states(self) -> int:
        return self.next_state.shape[0]

    @property
    def num_actions(self) -> int:
        return self.next_state.shape[1]

    def transition_matrix(self) -> torch.Tensor:
        """One-hot successors ``P[s, a, s'] = 1(next_state[s, a] == s')``, ``[S, A, S]`` float64."""
        return torch.nn.functional.one_hot(self.next_state, self.num_states).double()


def reachable_at(cmp: DeterministicCMP, step: int | None = None) -> torch.Tensor:
    """States that some action sequence reaches at exactly ``step`` (default: the horizon T), ``[S]`` bool.

    These are the goals a policy can hit at the last step (S_T below): the support of every achievable terminal
    marginal is inside this set, and every distribution on it is achievable (:func:`umrl.theory.policy_for_marginal`).
    """
    step = cmp.horizon if step is None else check_int("step", step, min=0)
    current = torch.zeros(cmp.num_states, dtype=torch.bool)
    current[cmp.start] = True
    for _ in range(step):
        following = torch.zeros_like(current)
        following[cmp.next_state[current].flatten()] = True
        current = following
    return current


def chain(length: int, horizon: int, *, start: int = 0) -> DeterministicCMP:
    """States ``0 .. length-1`` on a line; actions left, stay, right (a move off either end stays put)."""
    check_int("length", length, min=1)
    states = torch.arange(length)
    table = torch.stack([(states - 1).clamp(min=0), states, (states + 1).clamp(max=length - 1)], dim=1)
    return DeterministicCMP(table, start, horizon, name=f"chain{length}")


def grid(rows: int, columns: int, horizon: int, *, walls: tuple[tuple[int, int], ...] = (),
         start: tuple[int, int] = (0, 0)) -> DeterministicCMP:
    """A ``rows x columns`` grid; actions stay, up, down, left, right (:data:`GRID_MOVES`).

    A move into a wall cell or off the grid stays put. Wall cells are states no move enters (kept as states so that
    state ``s`` is cell ``(s // columns, s % columns)``); ``start`` must not be a wall.
    """
    check_int("rows", rows, min=1)
    check_int("columns", columns, min=1)
    blocked = set(walls)
    if tuple(start) in blocked or not (0 <= start[0] < rows and 0 <= start[1] < columns):
        raise InvalidValue("start", start, "a grid cell that is not a wall")
    table = torch.empty(rows * columns, len(GRID_MOVES), dtype=torch.long)
    for r in range(rows):
        for c in range(columns):
            for a, (dr, dc) in enumerate(GRID_MOVES):
                nr, nc = r + dr, c + dc
                inside = 0 <= nr < rows and 0 <= nc < columns and (nr, nc) not in blocked
                table[r * columns + c, a] = nr * columns + nc if inside else r * columns + c
    return DeterministicCMP(table, start[0] * columns + start[1], horizon, name=f"grid{rows}x{columns}",
                            shape=(rows, columns))


def tree(depth: int, branching: int = 2) -> DeterministicCMP:
    """A complete ``branching``-ary tree of ``depth`` levels below the root (the start); horizon = ``depth``.

    Action ``a`` moves to child ``a``; leaves loop on themselves. Every action sequence reaches its own leaf, so
    trajectories, terminal states and action sequences are in one-to-one correspondence.
    """
    check_int("depth", depth, min=1)
    check_int("branching", branching, min=1)
    num_internal = sum(branching ** d for d in range(depth))
    num_states = num_internal + branching ** depth
    table = torch.arange(num_states).unsqueeze(1).repeat(1, branching)
    parents = torch.arange(num_internal)
    table[:num_internal] = parents.unsqueeze(1) * branching + 1 + torch.arange(branching)
    return DeterministicCMP(table, 0, depth, name=f"tree{branching}^{depth}")


def random_cmp(num_states: int, num_actions: int, horizon: int, *, seed: int) -> DeterministicCMP:
    """Successors drawn uniformly at random (``torch.Generator`` seeded with ``seed``); start state 0."""
    check_int("num_states", num_states, min=1)
    check_int("num_actions", num_actions, min=1)
    generator = torch.Generator().manual_seed(check_int("seed", seed, min=0))
    table = torch.randint(num_states, (num_states, num_actions), generator=generator)
    return DeterministicCMP(table, 0, horizon, name=f"random{num_states}x{num_actions}s{seed}")
