"""Scale one meta-test SGD step of MAML initialisations: does a collapse come from the step's size or its direction?

    python scripts/diagnostics/step_size.py --step 2 --scales 0 0.125 0.25 0.5 1 \
        --run "full=results/point_nav/uml_diayn_paper/seed{seed}" \
        --run "10 %=results/point_nav/uml_diayn_trained_paper_batch/seed{seed}"
    python scripts/diagnostics/step_size.py --decompose --run "full=results/point_nav/uml_diayn_paper/seed{seed}"

The runs named here left the tree (results/README.md lists them); bring them back first:
``git checkout bbe1d9b -- results/point_nav/uml_diayn_paper results/point_nav/uml_diayn_trained_paper_batch``.

A diagnostic, not a method. Every run's policy (a MAML checkpoint, ``{seed}`` filled with each ``--seeds``) is
adapted as the suite's MAML cells are (:class:`umrl.metatest.protocol.TaskAdapter`: SGD at the checkpoint's inner lr
``α``, the reference schedule, the env's first ``--num-tasks`` evaluation tasks, meta-test seed = the run's seed) up
to the update ``--step`` (1: the first update, from the init; 2: the second, after a reference first step). That
update's gradient ``g`` is then taken at ``c · α`` for every ``c`` of ``--scales`` (the reference schedule takes
``c = 1`` at step 1 and ``c = 0.5`` later), and each result is rolled out with the same random numbers.

If the return falls only for large ``c`` and rises for small ones, the step overshoots (its size is wrong); if it
falls at every ``c > 0``, the direction is.

Printed per run and scale: IQM return over tasks × seeds after the scaled step, the RMS change of the action mean
``|Δμ|`` on the states of the batch the step was computed from (the step's size in action space), and the share of
those states whose new action mean lies outside the action bounds [-1, 1] (where a larger mean moves no faster).

``--decompose`` asks instead why the second update moves the action means further than the first at the same
scale. With ``θ0, B0`` the init and its batch and ``θ1, B1`` the parameters after the first update and their batch,
``u_B = ∂loss/∂μ`` is each batch's push on the action means (its advantages, at its own policy), and an update is
``θ − α J_θ(B)ᵀ u_B``. Printed per run and seed (``|Δμ|`` at scale 1, RMS over ``B``'s valid states of all tasks):

- ``|Δμ| θ·B`` for the four pairs: ``θ0·B0`` is the first update, ``θ1·B1`` the second's μ-part at scale 1;
  swapping the network (``θ1·B0``) or the batch (``θ0·B1``) tells which of the two makes the second one larger;
- ``|Σu|``: the size of each batch's summed push, RMS over tasks (the advantages are standardised);
- ``uniform``: the share of ``|Δμ|`` that the push's per-task mean, applied at every state, gives alone;
- ``response``: that uniform part's ``|Δμ|`` per unit of ``α |Σu|``, how strongly the network moves its means
  on the batch's states when all of them are pushed the same way;
- ``spread``: the RMS distance of the batch's observations from their task's mean observation;
- ``last layer``: the ``response`` if the uniform push moved only the last linear layer, whose change of the means
  is exact: ``Δμ(s) = −α Σu (h̄·h(s) + 1)`` with ``h(s)`` the features that layer reads and ``h̄`` their mean over
  the task's states (large when the features are large and point the same way);
- ``|h|``, ``|s|``: the RMS norm of those features and of the observations on the batch's states.
"""
from __future__ import annotations

import argparse

import numpy as np
import torch
from tensordict import TensorDictBase

from umrl.checkpoints import load_maml_policy
from umrl.checkpoints.labels import labelled_path
from umrl.envs.tasks import get_task_family
from umrl.metatest import AdaptationConfig
from umrl.metatest.protocol import TaskAdapter, make_eval_env
from umrl.metatest.stats import iqm
from umrl.objectives.policy_gradient import compute_advantages, episode_returns, vpg_loss
from umrl.process import tune_process
from umrl.rng import seed_everything


def make_adapter(path: str, *, env_name: str, tasks: torch.Tensor, seed: int,
                 config: AdaptationConfig) -> tuple[TaskAdapter, float]:
    """The SGD ``TaskAdapter`` of the init at ``path`` as the suite's MAML cells build it (its env is
    ``adapter.env``; close it when done) and ``α``."""
    policy, inner_lr = load_maml_policy(path)
    seed_everything(seed)
    env = make_eval_env(env_name, tasks, config.num_trajectories, seed=seed, horizon=config.horizon)
    return TaskAdapter(policy, env, tasks.shape[0], optimizer="sgd", lr=inner_lr, config=config), inner_lr


def mean_push(adapter: TaskAdapter, params: TensorDictBase, batch: TensorDictBase) -> torch.Tensor:
    """``∂loss/∂μ`` ``[T, N, H, A]``: the update's loss (``batch``'s advantages) differentiated in the action means
    ``params`` give; the step's gradient in the parameters is ``J_paramsᵀ`` of it."""
    dist_params = adapter.functional.dist_params(params.detach(), batch)
    loc = dist_params["loc"].detach().requires_grad_()
    dist_params = dist_params.set("loc", loc).set("scale", dist_params["scale"].detach())
    loss = vpg_loss(adapter.policy.build_dist_from_params(dist_params).log_prob(batch["action"]), batch).sum()
    return torch.autograd.grad(loss, loc)[0]


def mean_shift(adapter: TaskAdapter, params: TensorDictBase, batch: TensorDictBase, push: torch.Tensor,
               lr: float) -> float:
    """RMS ``|Δμ|`` on ``batch``'s valid states of the step ``params − lr · J_paramsᵀ push``."""
    moved = params.detach().clone()
    leaves = [p.requires_grad_() for p in moved.values(True, True) if p.is_floating_point()]
    loc = adapter.functional.dist_params(moved, batch)["loc"]
    gradients = torch.autograd.grad((loc * push).sum(), leaves, allow_unused=True)
    with torch.no_grad():
        for p, g in zip(leaves, gradients, strict=True):
            if g is not None:
                p.sub_(lr * g)
        new_loc = adapter.functional.dist_params(moved, batch)["loc"]
    mask = batch["mask"]
    return (new_loc - loc.detach())[mask].square().sum(-1).mean().sqrt().item()


def decompose(path: str, *, env_name: str, tasks: torch.Tensor, seed: int,
              config: AdaptationConfig) -> dict[str, float]:
    """The ``--decompose`` figures (module docstring) of the first two updates of the init at ``path``."""
    adapter, inner_lr = make_adapter(path, env_name=env_name, tasks=tasks, seed=seed, config=config)
    batched = adapter.functional.batched
    if batched is None:
        raise ValueError(f"{path}: --decompose needs a plain Gaussian MLP policy (BatchedGaussianMLP recognises it).")
    batches, params = [adapter.collect()], [adapter.params.detach().clone()]
    adapter.step(batches[0])  # writes the first batch's advantages
    params.append(adapter.params.detach().clone())
    batches.append(compute_advantages(adapter.collect(), gamma=config.gamma, lmbda=config.lmbda,
                                      normalize=config.normalize_advantage))
    pushes = [mean_push(adapter, theta, batch) for theta, batch in zip(params, batches, strict=True)]
    out = {}
    for i, theta in enumerate(params):
        for j, (batch, push) in enumerate(zip(batches, pushes, strict=True)):
            out[f"θ{i}·B{j}"] = mean_shift(adapter, theta, batch, push, inner_lr)
    for j, (theta, batch, push) in enumerate(zip(params, batches, pushes, strict=True)):
        valid = batch["mask"].unsqueeze(-1).to(push.dtype)
        count = valid.sum((1, 2), keepdim=True)
        total = (push * valid).sum((1, 2))  # [T, A]
        uniform = mean_shift(adapter, theta, batch, total[:, None, None] / count * valid, inner_lr)
        size = total.norm(dim=-1).square().mean().sqrt().item()
        obs = batch["observation"]
        centred = (obs - (obs * valid).sum((1, 2), keepdim=True) / count) * valid
        out[f"|Σu| B{j}"] = size
        out[f"uniform B{j}"] = uniform / out[f"θ{j}·B{j}"]
        out[f"response B{j}"] = uniform / (inner_lr * size)
        out[f"spread B{j}"] = (centred.square().sum() / valid.sum()).sqrt().item()
        # the uniform push moving the last linear layer alone: Δμ(s) = −α Σu (h̄·h(s) + 1), h̄ the task's mean feature
        with torch.no_grad():
            features = batched.features(theta, [batch.get(key) for key in adapter.functional.net.in_keys])
        mean_feature = (features * valid).sum((1, 2), keepdim=True) / count
        last = total.norm(dim=-1)[:, None, None] * ((features * mean_feature).sum(-1) + 1)
        out[f"last layer B{j}"] = (last[batch["mask"]].square().mean().sqrt() / size).item()
        out[f"|h| B{j}"] = features[batch["mask"]].norm(dim=-1).square().mean().sqrt().item()
        out[f"|s| B{j}"] = obs[batch["mask"]].norm(dim=-1).square().mean().sqrt().item()
    adapter.env.close()
    return out


def scaled_step(path: str, *, step: int, scales: list[float], env_name: str, tasks: torch.Tensor, seed: int,
                config: AdaptationConfig) -> dict[str, np.ndarray]:
    """Returns ``[S, T]``, RMS ``|Δμ|`` ``[S]`` and out-of-bounds share ``[S]`` of update ``step`` scaled by each
    of the ``S`` scales, for the init at ``path``."""
    adapter, inner_lr = make_adapter(path, env_name=env_name, tasks=tasks, seed=seed, config=config)
    for _ in range(step - 1):
        adapter.step(adapter.collect())
    batch = adapter.collect()
    before = adapter.params.detach().clone()
    adapter.step(batch)  # leaves the update's gradient in each leaf's .grad
    leaves = adapter.optimizer.param_groups[0]["params"]  # the per-task parameters the update moved
    gradients = [p.grad.clone() for p in leaves]
    mask = batch["mask"]
    loc_before = adapter.functional.dist_params(before, batch)["loc"][mask]
    rng_state = torch.get_rng_state()
    out = {"returns": [], "rms_shift": [], "out_of_bounds": []}
    for scale in scales:
        with torch.no_grad():
            adapter.params.update_(before)
            for p, g in zip(leaves, gradients, strict=True):
                p.sub_(scale * inner_lr * g)
            loc = adapter.functional.dist_params(adapter.params, batch)["loc"][mask]
        torch.set_rng_state(rng_state)  # every scale rolls out with the same random numbers
        out["returns"].append(episode_returns(adapter.collect()).mean(-1).numpy())
        out["rms_shift"].append((loc - loc_before).square().sum(-1).mean().sqrt().item())
        out["out_of_bounds"].append((loc.abs() > 1).any(-1).float().mean().item())
    adapter.env.close()
    return {key: np.asarray(value) for key, value in out.items()}


def print_decomposition(runs: list[tuple[str, str]], seeds: list[int], *, env_name: str, tasks: torch.Tensor,
                        config: AdaptationConfig) -> None:
    """The ``--decompose`` table: one row per run and seed, then each run's mean over seeds."""
    columns = ["θ0·B0", "θ1·B1", "θ1·B0", "θ0·B1", "|Σu| B0", "|Σu| B1", "uniform B0", "uniform B1",
               "response B0", "response B1", "spread B0", "spread B1", "last layer B0", "last layer B1",
               "|h| B0", "|h| B1", "|s| B0", "|s| B1"]
    print("first (B0) and second (B1) update at scale 1: RMS |Δμ| of θ − α J_θᵀ u_B on B's states, the summed "
          "push |Σu|, the uniform push's share of |Δμ|, its |Δμ| per unit α |Σu|, the states' spread, that response "
          "with only the last layer moved, the RMS norms of the features that layer reads and of the observations",
          flush=True)
    width = {c: max(12, len(c) + 2) for c in columns}
    print(f"{'run':<16}{'seed':>5}" + "".join(f"{c:>{width[c]}}" for c in columns), flush=True)
    for label, path in runs:
        results = [decompose(path.format(seed=seed), env_name=env_name, tasks=tasks, seed=seed, config=config)
                   for seed in seeds]
        for seed, values in [*zip(map(str, seeds), results, strict=True),
                             ("mean", {c: np.mean([r[c] for r in results]) for c in columns})]:
            print(f"{label:<16}{seed:>5}" + "".join(f"{values[c]:>{width[c]}.3f}" for c in columns), flush=True)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", action="append", required=True, type=labelled_path, metavar="LABEL=PATH",
                        help="a MAML run directory or checkpoint; {seed} is replaced by each seed")
    parser.add_argument("--step", type=int, choices=(1, 2, 3), default=2, help="the update to scale (1 = first)")
    parser.add_argument("--scales", nargs="+", type=float, default=[0.0, 0.125, 0.25, 0.5, 1.0],
                        metavar="C", help="multiples of the inner lr α to take the update at")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--env", default="point_nav")
    parser.add_argument("--num-tasks", type=int, default=20)
    parser.add_argument("--trajectories", type=int, default=20, help="per task and step (the quick profile's 20)")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--decompose", action="store_true",
                        help="print why the second update is larger than the first (module docstring) instead")
    args = parser.parse_args(argv)
    if any(scale < 0 for scale in args.scales):
        parser.error(f"--scales: got {args.scales}; expected values >= 0")
    torch.set_num_threads(args.threads)
    tune_process()
    config = AdaptationConfig(num_steps=args.step, num_trajectories=args.trajectories, sgd_schedule="reference")
    tasks = get_task_family(args.env).eval_tasks(args.num_tasks)
    if args.decompose:
        print_decomposition(args.run, args.seeds, env_name=args.env, tasks=tasks, config=config)
        return
    print(f"update {args.step} taken at c × α; IQM return over tasks × seeds after it, RMS |Δμ| on the batch's "
          "states, share of new means outside [-1, 1]", flush=True)
    print(f"{'run':<16}{'seed':>5}" + "".join(f"{f'c={c:g}':>24}" for c in args.scales), flush=True)
    for label, path in args.run:
        results = [scaled_step(path.format(seed=seed), step=args.step, scales=args.scales, env_name=args.env,
                               tasks=tasks, seed=seed, config=config) for seed in args.seeds]
        rows = [(str(seed), [r]) for seed, r in zip(args.seeds, results, strict=True)] + [("all", results)]
        for seed, group in rows:
            returns = iqm(np.concatenate([r["returns"] for r in group], axis=1), axis=1)
            shift = np.mean([r["rms_shift"] for r in group], axis=0)
            bounds = np.mean([r["out_of_bounds"] for r in group], axis=0)
            cells = "".join(f"{f'{g:.1f} | {s:.2f} | {b:.2f}':>24}" for g, s, b in zip(returns, shift, bounds,
                                                                                          strict=True))
            print(f"{label:<16}{seed:>5}{cells}", flush=True)


if __name__ == "__main__":
    main()
