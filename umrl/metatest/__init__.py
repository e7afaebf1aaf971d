"""Meta-test: adapt each method's initialisation on held-out tasks and report the results.

=================  ===========================================================================================
module             job
=================  ===========================================================================================
``protocol``       the adaptation protocol: :class:`AdaptationConfig`, :class:`TaskAdapter` (batched per-task
                   updates, SGD schedule), DIAYN-init's :func:`select_skills`, the learning-rate sweep
``method_table``   the method registry: :data:`METHODS` of typed :class:`Method` / :class:`Pretraining` records
``methods``        :func:`load_initialisation`, the typed :class:`CellSpec` and :func:`run_cell`
``results``        tidy rows / CSV, curves, the summary and ablation tables, the suite's ``summary.md``
``stats``          AUC, IQM, bootstrap confidence intervals
``plots``          adaptation-curve and ablation figures
``provenance``     commit, command and hardware of a run
=================  ===========================================================================================
"""
from umrl.metatest.method_table import METHODS, RECIPES, Method, Pretraining, default_lr_schedule, get_method
from umrl.metatest.methods import (
    PROPOSALS,
    CellSpec,
    Initialisation,
    SweepConfig,
    load_initialisation,
    meta_test,
    run_cell,
)
from umrl.metatest.plots import METHOD_COLORS, Curve, plot_ablation, plot_adaptation_curves
from umrl.metatest.protocol import (
    DEFAULT_SGD_SCHEDULE,
    OPTIMIZERS,
    SGD_SCHEDULES,
    SWEEP_SEED_OFFSET,
    AdaptationConfig,
    TaskAdapter,
    make_eval_env,
    select_skills,
    sgd_lr_factor,
    sweep_learning_rate,
    sweep_tasks,
)
from umrl.metatest.provenance import provenance
from umrl.metatest.results import (
    COLUMNS,
    ablation_curves,
    ablation_table,
    arm_label,
    arm_styles,
    baseline_arms,
    cell_finished,
    curves_from_rows,
    mean_curve,
    pretraining_note,
    read_rows,
    run_matrix,
    suite_summary,
    summary_table,
    to_rows,
    write_rows,
)
from umrl.metatest.stats import auc, bootstrap_ci, iqm, summarize

__all__ = [
    "COLUMNS",
    "DEFAULT_SGD_SCHEDULE",
    "METHODS",
    "METHOD_COLORS",
    "OPTIMIZERS",
    "PROPOSALS",
    "RECIPES",
    "SGD_SCHEDULES",
    "SWEEP_SEED_OFFSET",
    "AdaptationConfig",
    "CellSpec",
    "Curve",
    "Initialisation",
    "Method",
    "Pretraining",
    "SweepConfig",
    "TaskAdapter",
    "ablation_curves",
    "ablation_table",
    "arm_label",
    "arm_styles",
    "auc",
    "baseline_arms",
    "bootstrap_ci",
    "cell_finished",
    "curves_from_rows",
    "default_lr_schedule",
    "get_method",
    "iqm",
    "load_initialisation",
    "make_eval_env",
    "mean_curve",
    "meta_test",
    "plot_ablation",
    "plot_adaptation_curves",
    "pretraining_note",
    "provenance",
    "read_rows",
    "run_cell",
    "run_matrix",
    "select_skills",
    "sgd_lr_factor",
    "suite_summary",
    "summarize",
    "summary_table",
    "sweep_learning_rate",
    "sweep_tasks",
    "to_rows",
    "write_rows",
]
