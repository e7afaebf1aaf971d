"""How the share of the batch behind TRPO's KL Hessian changes the MAML meta-step, on one batch.

    python scripts/diagnostics/kl_hessian_fraction.py --fractions 1.0 0.1 --draws 3 \
        --run "paper=results/point_nav/uml_diayn_paper/seed{seed}" \
        --run "10 %=results/point_nav/uml_diayn_trained_paper_batch/seed{seed}" \
        --run "iteration 0=results/point_nav/uml_diayn_paper/seed{seed}:init" \
        --skills "results/point_nav/diayn_trained_skills/seed{seed}"

The runs named here left the tree (results/README.md lists them); bring them back first:
``git checkout bbe1d9b -- results/point_nav/uml_diayn_paper results/point_nav/uml_diayn_trained_paper_batch results/point_nav/diayn_trained_skills``.

A diagnostic, not a method. For every run (a MAML checkpoint, ``{seed}`` filled with each ``--seeds``; ``:init``
keeps the run's config but starts from the recipe's own initialisation for that seed, iteration 0) the MAML recipe's
pieces (``umrl.trainers.maml.build``, ``meta_batch``, ``meta_step``) collect **one** meta-batch with the checkpoint's
config (on the CPU, no CUDA graphs; ``--skills`` replaces a DIAYN proposal's skills path, e.g. with the committed
exports), then take the TRPO meta-step from the same parameters on that same batch once per ``--fractions`` value
(``trpo.hvp_fraction``: the share of trajectories behind the KL Hessian; fractions below 1 with ``--draws``
different subsamples). Each step is undone before the next, so the steps differ only in the Hessian.

Printed per step: accepted, line-search trials (of them: KL over ``max_kl`` / no improvement), the measured KL and
surrogate improvement; the change of the mean log-std ``Δ log σ`` (the policy's state-independent log-std, mean over
action dimensions); ``KL(σ)``, the KL between the policy before and after the step from the log-std change alone
(``Σ_d Δ_d + (exp(-2 Δ_d) - 1) / 2``, the means held fixed), as a share of ``trpo.max_kl``; the step's norm on the
mean network; and its cosine with the first fraction's step (``nan`` where either step was rejected). A summary
gives the medians over seeds and draws (the cosine's over the steps that have one). The question it answers: does a
step whose KL Hessian sees the whole batch spend its trust region differently, e.g. shrink σ faster, than one that
sees 10 %?
"""
from __future__ import annotations

import argparse
import math
import statistics

import torch
from omegaconf import OmegaConf

from umrl.checkpoints import load_maml_checkpoint
from umrl.checkpoints.labels import labelled_path
from umrl.configs import validate
from umrl.configs.maml import MAMLConfig
from umrl.modules import policy_log_std
from umrl.objectives.maml import gaussian_kl
from umrl.optim.meta_hvp import make_meta_hvp
from umrl.process import tune_process
from umrl.rng import seed_everything
from umrl.trainers.maml import build, meta_batch, meta_step

BATCH_SEED_OFFSET = 1000  # the batch's streams differ from the recipe's (seed_everything(seed)) but not between runs


def run_config(state: dict, *, threads: int, skills: str | None):
    """The checkpoint's resolved config, moved to the CPU without logging (and onto ``skills`` if given)."""
    cfg = OmegaConf.create(state["config"])
    overrides = {"device": "cpu", "cudagraphs": False, "num_threads": threads, "progress": False,
                 "logger": {"backend": "none"}}
    if skills is not None and cfg.proposal == "diayn":
        overrides["diayn_checkpoint"] = skills
    return validate(OmegaConf.merge(cfg, overrides), MAMLConfig)


def sigma_kl(delta: torch.Tensor) -> float:
    """KL(N(μ, σ) ‖ N(μ, σ e^Δ)) summed over action dimensions: what a log-std change ``delta`` costs alone."""
    zeros, ones = torch.zeros_like(delta), torch.ones_like(delta)
    return gaussian_kl(zeros, ones, zeros, delta.exp()).item()


def compare_steps(path: str, *, from_init: bool, seed: int, fractions: list[float], draws: int, threads: int,
                  skills: str | None) -> list[dict]:
    """One row per step (fraction × draw) from the run at ``path`` on one meta-batch drawn with ``seed``."""
    state = load_maml_checkpoint(path)
    cfg = run_config(state, threads=threads, skills=skills)
    torch.set_num_threads(cfg.num_threads)
    seed_everything(cfg.seed)  # as the recipe: its iteration-0 policy for a run started with this config
    proposal, policy, loss, trpo = build(cfg)
    if not from_init:
        policy.load_state_dict(state["policy"])
    generator = seed_everything(BATCH_SEED_OFFSET + seed)
    support, adapted, query, _ = meta_batch(cfg, proposal, policy, loss, generator)
    params, log_std = list(policy.parameters()), policy_log_std(policy)
    is_log_std = [p is log_std for p in params]
    log_std_index = is_log_std.index(True)
    start = [p.detach().clone() for p in params]
    rows, reference = [], None
    for fraction in fractions:
        for draw in range(draws if fraction < 1 else 1):
            if rows:  # undo the last step; the inner step's graph went with it
                with torch.no_grad():
                    for p, p0 in zip(params, start):
                        p.copy_(p0)
                with torch.enable_grad():
                    adapted = loss.adapt(support)
            cfg.trpo.hvp_fraction = fraction
            trpo.hvp = make_meta_hvp(cfg.trpo.hvp, loss, fraction=fraction, generator=torch.Generator().manual_seed(draw))
            info = meta_step(cfg, loss, trpo, support, query, adapted)
            diffs = [p.detach() - p0 for p, p0 in zip(params, start)]
            step = torch.cat([d.reshape(-1) for d in diffs])
            reference = step if reference is None else reference
            delta = diffs[log_std_index]
            rows.append({
                "seed": seed, "fraction": fraction, "draw": draw, "accepted": info["accepted"],
                "backtracks": info["backtracks"], "rejected_kl": info["rejected_kl"],
                "rejected_surrogate": info["rejected_surrogate"], "kl": info["kl"], "improvement": info["improvement"],
                "log_std": start[log_std_index].mean().item(), "dlogstd": delta.mean().item(),
                "kl_sigma": sigma_kl(delta) / cfg.trpo.max_kl,
                "mean_net_norm": torch.cat([d.reshape(-1) for d, s in zip(diffs, is_log_std) if not s]).norm().item(),
                "cosine": torch.nn.functional.cosine_similarity(step, reference, dim=0).item()
                if step.any() and reference.any() else math.nan,  # a rejected step has no direction
            })
    proposal.env.close()
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", action="append", required=True, type=labelled_path, metavar="LABEL=PATH[:init]",
                        help="a MAML run directory or checkpoint; {seed} is replaced by each seed")
    parser.add_argument("--fractions", nargs="+", type=float, default=[1.0, 0.1])
    parser.add_argument("--draws", type=int, default=3, help="subsamples per fraction below 1")
    parser.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    parser.add_argument("--skills", help="DIAYN skills for DIAYN proposals; {seed} is replaced")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    runs = [(label, path.removesuffix(":init"), path.endswith(":init")) for label, path in args.run]
    bad = [f for f in args.fractions if not 0 < f <= 1]
    if bad:
        parser.error(f"--fractions: got {bad}; expected values in (0, 1]")
    tune_process()
    summary = {}
    print("run | seed | fraction | draw | accepted | trials (KL over / no improvement) | KL | improvement | "
          "log σ before | Δ log σ | KL(σ) / max_kl | ‖Δ mean net‖ | cos vs first")
    for label, path, from_init in runs:
        for seed in args.seeds:
            skills = args.skills.format(seed=seed) if args.skills else None
            for row in compare_steps(path.format(seed=seed), from_init=from_init, seed=seed,
                                     fractions=args.fractions, draws=args.draws, threads=args.threads,
                                     skills=skills):
                summary.setdefault((label, row["fraction"]), []).append(row)
                print(f"{label} | {seed} | {row['fraction']:g} | {row['draw']} | {row['accepted']:.0f} | "
                      f"{row['backtracks']:.0f} ({row['rejected_kl']:.0f} / {row['rejected_surrogate']:.0f}) | "
                      f"{row['kl']:.5f} | {row['improvement']:.5f} | "
                      f"{row['log_std']:.3f} | {row['dlogstd']:+.5f} | {row['kl_sigma']:.3f} | "
                      f"{row['mean_net_norm']:.4f} | {row['cosine']:.3f}", flush=True)
    print(f"\nmedians over seeds {args.seeds} and draws:")
    print("run | fraction | steps accepted | Δ log σ | KL(σ) / max_kl | ‖Δ mean net‖ | cos vs first")
    for (label, fraction), rows in summary.items():
        med = {k: statistics.median(r[k] for r in rows) for k in ("dlogstd", "kl_sigma", "mean_net_norm")}
        cosines = [r["cosine"] for r in rows if not math.isnan(r["cosine"])]
        cosine = f"{statistics.median(cosines):.3f}" if cosines else "–"
        accepted = sum(r["accepted"] for r in rows)
        print(f"{label} | {fraction:g} | {accepted:.0f} / {len(rows)} | {med['dlogstd']:+.5f} | "
              f"{med['kl_sigma']:.3f} | {med['mean_net_norm']:.4f} | {cosine}")


if __name__ == "__main__":
    main()
