"""The benchmark suite: does unsupervised meta-learning make RL faster here?

:func:`run_suite` runs UML-DIAYN, UML-random, oracle, VIME-init, DIAYN-init and scratch on the chosen envs and seeds
for a suite config (``umrl suite`` or ``benchmarks/suite.py`` is its command line, with the configs in
:data:`CONFIG_DIR`).

0. **Validation**: the config is checked against :class:`umrl.configs.suite.SuiteConfig` and every recipe config
   the suite will run is composed (``umrl.trainers.compose``) and checked against its schema, so every bad key or value
   is listed before any work starts.
1. **Pre-training** (jobs): DIAYN, VIME and MAML with each proposal (diayn after its DIAYN run, which is not trained
   when only reused UML-DIAYN runs would read it), each
   ``umrl.trainers.<recipe>.train(cfg)`` in a worker process, its config composed from the recipe's own yaml with the
   suite's settings and ``pretrain.<recipe>.overrides``. Each run lives in
   ``pretrain/<kind>/<env>/seed<s>-<key>/``, ``<key>`` a hash of its resolved config and the code version
   (:mod:`umrl.metatest.cache`): a finished run (marker ``suite_complete``, or a checkpoint at the final step) is
   reused, a killed one resumes from its last checkpoint, a changed config or code gets a new run.
   ``pretrain.<recipe>.reuse`` points at existing runs instead (path templates with ``{env}``, ``{seed}``,
   ``{proposal}``; a ``num_skills`` override such a run was not trained with is refused). Meta-test seed
   ``seeds[i]`` uses the runs of pre-training seed ``pretrain_seeds[i]`` (null: the same seed, independent
   pre-training per seed).
2. **Meta-test cells**: each (method, env, seed) -- and, for the SGD methods, each ``protocol.sgd_schedule`` -- is
   an independent job running :func:`umrl.metatest.run_cell` on a typed :class:`umrl.metatest.CellSpec`; its CSV
   ``cells/<env>/<method>/seed<s>[.<schedule>]-<key>.csv`` (key: the spec, its checkpoint and the code version)
   appears atomically when it finishes and is never recomputed, so a killed suite resumes.
3. **Meta-training ablation**: the kept MAML checkpoints along meta-training are meta-tested the same way.
4. **Reports** (built by :mod:`umrl.metatest.results`) under ``output_dir`` from the cells of *this* config only:
   ``results.csv`` (tidy: method, env, seed, task, step, return, length, lr_schedule), ``summary.md`` (return at
   k = 0, 1, 5, K and AUC: IQM and mean with bootstrap CIs; mean episode length at k = 0 and K where episodes end
   early; pre-training seeds; commit, command, hardware and wall time), ``curves.png``, ``ablation.png`` /
   ``ablation.md``, ``config.yaml`` (the validated config) and wandb runs (offline by default, under
   ``output_dir/wandb``) in one group per suite run.

Modules: :mod:`umrl.suite.plan` (jobs and their keys), :mod:`umrl.suite.report` (tables, figures, wandb),
:mod:`umrl.suite.run` (:func:`run_suite`), :mod:`umrl.suite.verdicts` (the verdict rule over committed cells, a
command: ``python -m umrl.suite.verdicts results/``), :mod:`umrl.suite.export` (a suite's cells into that layout:
``python -m umrl.suite.export <output_dir> <env> results/<env>``). The suite plans and reports only: the jobs run through :mod:`umrl.launch`, what a cell computes and how results are
tabulated live in :mod:`umrl.metatest`. Jobs run as fresh worker processes (``launcher.workers`` at a time; their
output goes to ``logs/<job>.log``), in this process (``launcher.workers=0``) or as Ray tasks when ``launcher.ray_address`` is set
(``local`` starts a Ray instance on this machine). The local workers are plain subprocesses (no multiprocessing
semaphores: a suite killed with SIGKILL leaves nothing in ``/dev/shm``). A failed job is printed with its error and
the tail of its log. Every value is a config override (:data:`CONFIG_DIR`).
"""
from pathlib import Path

from umrl.suite.plan import (
    BUDGET_KEYS,
    PretrainRun,
    cell_spec,
    checkpoint_identity,
    hydra_overrides,
    keyed_cell,
    plan,
    plan_ablation,
    plan_pretraining,
    pretrain_key,
    sgd_schedules,
)
from umrl.suite.report import report, summarize_timings
from umrl.suite.run import code_version, run_suite, suite_group

CONFIG_DIR = Path(__file__).resolve().parent / "config"
"""The suite's Hydra configs, installed with the package: ``suite.yaml`` (every key, with its comment) and the
``profile/`` presets (``tiny``, ``quick``, ``reference``)."""

__all__ = ["BUDGET_KEYS", "CONFIG_DIR", "PretrainRun", "cell_spec", "checkpoint_identity", "code_version",
           "hydra_overrides", "keyed_cell", "plan", "plan_ablation", "plan_pretraining", "pretrain_key", "report", "run_suite",
           "sgd_schedules", "suite_group", "summarize_timings"]
