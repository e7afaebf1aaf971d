"""Where a trajectory in a batched rollout ends, and a batch's valid steps packed into fewer rows: the lowest-level
helpers shared by collection, the trainers and the losses."""
from __future__ import annotations

import torch
from tensordict import TensorDictBase

__all__ = ["pack_valid_steps", "trajectory_mask"]


def trajectory_mask(done: torch.Tensor) -> torch.Tensor:
    """``[..., H]`` bool: step ``t`` belongs to the first episode (no ``done`` strictly before ``t``).

    Args:
        done: ``("next", "done")`` of shape ``[..., H, 1]``.
    """
    if done.shape[-1] != 1:
        raise ValueError(f"done must have a trailing singleton dim [..., H, 1], got {tuple(done.shape)}.")
    done = done.squeeze(-1).long()
    return (done.cumsum(-1) - done) == 0


def pack_valid_steps(batch: TensorDictBase, mask_key: str = "mask") -> TensorDictBase:
    """Each task's valid steps of ``batch`` ``[T, M, H]``, in order, moved into as few rows of ``H`` as they fill.

    A batch of fixed env steps whose episodes end early (:func:`umrl.rollout.collect_env_steps`) pads every task to
    the most episodes any task has, and every episode to the horizon: the oracle's point_nav batches grew to 3.9 ×
    their valid steps. Per-task means over the valid steps (the inner loss, the surrogate, the KL, the Hessian-vector
    products) are the same on the packed batch, up to the order of the sums. Rows are no longer episodes: episode
    returns and lengths need the batch before packing.

    Returns:
        ``[T, R, H]`` with ``R = ceil(max_t valid_t / H)``: row ``r`` of task ``t`` holds its valid steps
        ``r·H .. r·H + H - 1``; ``mask_key`` is true on the first ``valid_t`` of them, the rest repeat masked-out steps
        of the batch. ``batch`` itself when packing would not drop a row (a batch of full episodes is returned
        unchanged, so its numbers are exactly those of the unpacked layout).

    Example:
        >>> from tensordict import TensorDict
        >>> mask = torch.tensor([[[1, 1, 0, 0], [1, 0, 0, 0], [1, 1, 1, 0]]], dtype=torch.bool)  # [1, 3, 4]
        >>> step = torch.arange(12).reshape(1, 3, 4)
        >>> packed = pack_valid_steps(TensorDict({"mask": mask, "step": step}, batch_size=[1, 3, 4]))
        >>> packed["step"][packed["mask"]].tolist(), packed.shape
        ([0, 1, 4, 8, 9, 10], torch.Size([1, 2, 4]))
    """
    if batch.batch_dims != 3:
        raise ValueError(f"batch must be [T, M, H], got batch size {tuple(batch.batch_size)}.")
    num_tasks, rows, horizon = batch.batch_size
    mask = batch.get(mask_key).reshape(num_tasks, rows * horizon)
    valid = mask.sum(-1)
    packed_rows = -(-int(valid.max()) // horizon)
    if packed_rows >= rows:
        return batch
    order = torch.argsort((~mask).to(torch.uint8), dim=-1, stable=True)[:, : packed_rows * horizon]  # valid first
    task = torch.arange(num_tasks, device=order.device).unsqueeze(-1)
    packed = batch.reshape(num_tasks, rows * horizon)[task, order]
    packed.set(mask_key, torch.arange(packed_rows * horizon, device=valid.device) < valid.unsqueeze(-1))
    return packed.reshape(num_tasks, packed_rows, horizon)
