"""Where a trajectory in a batched rollout ends: the lowest-level helper shared by collection and the losses."""
from __future__ import annotations

import torch

__all__ = ["trajectory_mask"]


def trajectory_mask(done: torch.Tensor) -> torch.Tensor:
    """``[..., H]`` bool: step ``t`` belongs to the first episode (no ``done`` strictly before ``t``).

    Args:
        done: ``("next", "done")`` of shape ``[..., H, 1]``.
    """
    if done.shape[-1] != 1:
        raise ValueError(f"done must have a trailing singleton dim [..., H, 1], got {tuple(done.shape)}.")
    done = done.squeeze(-1).long()
    return (done.cumsum(-1) - done) == 0
