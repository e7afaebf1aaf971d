"""The suite's reports from its finished cells: ``results.csv``, ``summary.md``, ``curves.png``, the meta-training
ablation (``ablation.png`` / ``ablation.md``) and wandb runs (one per env and arm, plus the report's figures); tables
and figures are :mod:`umrl.metatest.results`' and :mod:`umrl.metatest.plots`'.
"""
from __future__ import annotations

import json
import shlex
import sys
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from umrl.atomic_write import write_text_atomic
from umrl.configs.suite import pretrain_seeds
from umrl.loggers import close_logger, log_image, log_metrics, log_table, make_logger
from umrl.metatest import (
    Curve,
    ablation_curves,
    ablation_table,
    arm_label,
    arm_styles,
    baseline_arms,
    bootstrap_ci,
    curves_from_rows,
    iqm,
    plot_ablation,
    plot_adaptation_curves,
    pretraining_note,
    provenance,
    read_rows,
    run_matrix,
    suite_summary,
    summary_table,
    write_rows,
)
from umrl.plain_config import to_container

__all__ = ["CURVE_COLUMNS", "report", "summarize_timings"]


def report(cfg: DictConfig, group: str, timings: Mapping[str, float], cells: Sequence[Path],
           ablation: Sequence[Path] = (), *, wall_seconds: float) -> str:
    """Write results.csv, summary.md, curves.png (+ ablation) from this config's ``cells`` and ``ablation`` CSVs
    (missing ones are left out: failed jobs) and log them to wandb; returns the markdown."""
    out = Path(cfg.output_dir)
    cells = [Path(p) for p in cells if Path(p).exists()]
    rows = read_rows(cells)
    if not rows:
        raise RuntimeError(f"no finished cells under {out / 'cells'}: nothing to report (see {out / 'logs'}).")
    write_rows(rows, out / "results.csv")
    table, records = summary_table(rows, steps=list(cfg.report.steps), methods=list(cfg.methods))
    curves = curves_from_rows(rows, methods=list(cfg.methods))
    plot_adaptation_curves(curves, out / "curves.png", styles=arm_styles(rows))
    settings = OmegaConf.to_yaml(OmegaConf.create({k: to_container(cfg)[k] for k in (
        "envs", "methods", "seeds", "pretrain_seeds", "num_tasks", "protocol", "adam_lr", "sgd_lr", "sweep",
        "device")}))
    lrs, before = {}, {}
    for p in cells:
        if p.with_suffix(".json").exists():
            info = json.loads(p.with_suffix(".json").read_text())
            label = arm_label(info["method"], info.get("lr_schedule", "constant"))
            lrs.setdefault((info["env"], label), set()).add(round(info["lr"], 6))
            if "skill_choice_env_steps" in info:
                before.setdefault((info["env"], label), set()).add(info["skill_choice_env_steps"])
    edges = {min(cfg.sweep.lrs), max(cfg.sweep.lrs)} if cfg.sweep.enabled else set()
    lr_lines = [f"- {env} / {method}: lr {sorted(v)}" + (" (an edge of sweep.lrs: the best may lie beyond)"
                                                          if v & edges else "") for (env, method), v in sorted(lrs.items())]
    lr_lines += [f"- {env} / {method}: {', '.join(map(str, sorted(v)))} env steps per task before k = 0 (choosing "
                 "its skill), on no curve" for (env, method), v in sorted(before.items())]
    time_lines = [f"- {k}: {v:.0f} s" for k, v in timings.items()] + [
        "", "(Jobs run with launcher.workers in parallel; per-job times of every invocation are in timings.json.)"]
    ablation_rows = read_rows([Path(p) for p in ablation if Path(p).exists()])
    ablation_md = None
    if ablation_rows:
        along_training = ablation_curves(ablation_rows, metric="auc")
        baselines = baseline_arms(ablation_rows)
        styles = {arm: {**style, **({"linestyle": ":", "marker": None} if arm in baselines else {})}
                  for arm, style in arm_styles(ablation_rows).items()}
        plot_ablation(along_training, out / "ablation.png",
                      metric=f"meta-test AUC (k = 0..{cfg.ablation.num_steps})", styles=styles)
        ablation_md = ablation_table(along_training, baselines)
        write_text_atomic(out / "ablation.md", ablation_md)
    record = provenance(command=shlex.join([Path(sys.executable).name, *sys.argv]), wall_seconds=wall_seconds,
                        job_threads=int(cfg.launcher.threads))
    markdown = suite_summary(table, profile=cfg.profile_name, pretraining=pretraining_note(
        list(cfg.seeds), pretrain_seeds(cfg)), lr_lines=lr_lines, time_lines=time_lines, settings_yaml=settings,
        provenance=record, ablation=ablation_md)
    write_text_atomic(out / "summary.md", markdown)
    _log_to_wandb(cfg, group, curves, rows, records, out)
    return markdown


CURVE_COLUMNS = ["k", "env", "method", "iqm", "iqm_low", "iqm_high", "mean", "mean_low", "mean_high"]
"""The columns of the meta-test curve tables: per adaptation step ``k`` of one (env, arm), the IQM over its (seed,
task) runs and the mean (as in ``curves.png``), each with its 95% bootstrap CI."""


def _curve_rows(rows: Sequence[Mapping], env: str, method: str, curve: Curve) -> list[list]:
    """The :data:`CURVE_COLUMNS` rows of one (env, arm): IQMs and CIs from its results ``rows`` (the summary
    table's, at every k), means and CIs from its ``curve`` (:func:`~umrl.metatest.curves_from_rows`')."""
    per_k = run_matrix(rows, env=env, method=method).T  # [K + 1, runs]
    table = []
    for k, values in enumerate(per_k):
        low, high = bootstrap_ci(values, iqm)
        table.append([k, env, method, float(iqm(values)), float(low), float(high), float(curve.mean[k]),
                      float(curve.low[k]), float(curve.high[k])])
    return table


def _log_to_wandb(cfg: DictConfig, group: str, curves, rows: Sequence[Mapping], records: Sequence[Mapping],
                  out: Path) -> None:
    """wandb runs in the suite's ``group``, each with the suite's whole config: one ``meta_test`` run per (env, arm)
    of ``curves`` (config also ``method``, ``env``) and one ``report`` run.

    An arm's run holds its mean return per k as the scalar ``meta_test/return``, its curve with the 95% band as the
    table ``meta_test/curve`` (:data:`CURVE_COLUMNS`, from its (seed, task) runs ``rows``) and as the image
    ``meta_test/curve_band`` (its panel of ``curves.png``: the mean and its band), the IQMs of ``records``
    (:func:`~umrl.metatest.summary_table`'s) as ``summary/<metric>_iqm`` and its records as the table ``results``.
    The report run holds every record (``results``), every arm's curve rows (``meta_test/curves``) and the figures.
    Runs land in ``<out>/wandb`` (the suite sets ``WANDB_DIR`` unless the user did)."""
    config = to_container(cfg)
    logger_cfg = {**config["logger"], "group": group}
    columns = list(dict.fromkeys(key for record in records for key in record))
    styles = arm_styles(rows)

    def table(selected: Sequence[Mapping]) -> list[list]:
        return [[record.get(key) for key in columns] for record in selected]

    every_curve = []
    with tempfile.TemporaryDirectory() as figures:  # log_image gives each run its own copy of a figure
        for env, methods in curves.items():
            for method, curve in methods.items():
                logger = make_logger(logger_cfg, exp_name=f"{method}_{env}".replace(" ", "_"), job_type="meta_test",
                                     config={**config, "method": method, "env": env}, log_dir=out)
                for k, mean in enumerate(curve.mean):
                    log_metrics(logger, {"meta_test/return": mean}, step=k)
                mine = [r for r in records if r["env"] == env and r["method"] == method]
                log_metrics(logger, {f"summary/{r['metric']}_iqm": r["iqm"] for r in mine}, step=len(curve.mean) - 1)
                arm_curve = _curve_rows(rows, env, method, curve)
                every_curve += arm_curve
                log_table(logger, "meta_test/curve", CURVE_COLUMNS, arm_curve)
                if getattr(getattr(logger, "experiment", None), "disabled", True) is False:  # a wandb run that keeps it
                    band = plot_adaptation_curves({env: {method: curve}}, Path(figures) / "band.png",
                                                  styles={method: styles[method]})
                    log_image(logger, "meta_test/curve_band", band, step=len(curve.mean) - 1)
                log_table(logger, "results", columns, table(mine))
                close_logger(logger)
    logger = make_logger(logger_cfg, exp_name="report", job_type="report", config=config, log_dir=out)
    log_table(logger, "results", columns, table(records))
    log_table(logger, "meta_test/curves", CURVE_COLUMNS, every_curve)
    for name in ("curves", "ablation"):
        if (out / f"{name}.png").exists():
            log_image(logger, f"report/{name}", out / f"{name}.png", step=0)
    close_logger(logger)


def summarize_timings(history: Sequence[Mapping]) -> dict[str, float]:
    """Wall times for the report: each invocation, each pre-training job and the mean cell (latest successful runs)."""
    jobs: dict[str, float] = {}
    for invocation in history:
        jobs.update(invocation["jobs"])
    timings = {f"suite invocation {i + 1} (wall)": inv["wall"] for i, inv in enumerate(history)}
    timings.update({k: v for k, v in jobs.items() if k.startswith("pretrain/")})
    for prefix in ("cell/", "ablation/"):
        cells = [v for k, v in jobs.items() if k.startswith(prefix)]
        if cells:
            timings[f"{prefix}* ({len(cells)} jobs, mean per job)"] = sum(cells) / len(cells)
    return timings
