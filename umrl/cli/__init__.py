"""umrl's command lines: ``umrl <command> [Hydra overrides]``, the console script a pip install puts on the PATH.

    umrl diayn +profile=diayn_tiny                 # DIAYN skills (the task proposal)
    umrl maml +profile=maml_tiny proposal=diayn    # MAML meta-training on them (UML-DIAYN), or proposal=random|oracle
    umrl vime +profile=vime_tiny                   # VIME pre-training (the VIME-init baseline)
    umrl suite profile=tiny                        # the benchmark suite: every method, meta-test, reports
    umrl maml --help                               # a command's config, every key with its comment

Each command takes the overrides, flags (``-m``, ``--cfg job``, ``--help``) and config of its checkout script
(``python recipes/<command>.py``, ``python benchmarks/suite.py``), which call the same :func:`run`; ``python -m umrl``
is the same command line. One Hydra app per command, in :mod:`umrl.cli.diayn`, :mod:`umrl.cli.maml`,
:mod:`umrl.cli.vime` and :mod:`umrl.cli.suite` (one module each, so that Hydra names each run's log after its
command: ``hydra/maml.log``).

A bad value or an unknown key ends the command before any work with the lines of
:class:`umrl.configs.ConfigError` (``key: got <value>; expected <what is accepted>``; a misspelt key gets "did you
mean"), exit status 1 and no traceback; ``HYDRA_FULL_ERROR=1`` raises the error with its full traceback instead
(:mod:`umrl.cli.errors`).
"""
from __future__ import annotations

import difflib
import importlib
import sys
from collections.abc import Sequence

COMMANDS = {
    "diayn": "DIAYN skill discovery: skill-conditioned SAC and a skill discriminator (the task proposal)",
    "maml": "MAML meta-training on proposed tasks: proposal=diayn|random|oracle",
    "vime": "VIME pre-training: TRPO on the information-gain bonus (the VIME-init baseline)",
    "suite": "the benchmark suite: pre-training, meta-test of every method, reports",
}
"""Each command, with the line ``umrl --help`` prints for it."""

__all__ = ["COMMANDS", "main", "run"]


def usage() -> str:
    lines = [f"  {name:<6} {what}" for name, what in COMMANDS.items()]
    return "\n".join(["usage: umrl <command> [key=value ...]  (Hydra overrides and flags; umrl <command> --help)",
                      "", "commands:", *lines])


def main(argv: Sequence[str] | None = None) -> None:
    """The ``umrl`` console script: ``argv`` (default ``sys.argv[1:]``) is a command of :data:`COMMANDS`, then that
    command's Hydra arguments. Hydra reads its arguments from ``sys.argv``, so this sets ``sys.argv`` to them (the
    command owns the process)."""
    args = list(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(usage())
        return
    command, *rest = args
    if command not in COMMANDS:
        close = difflib.get_close_matches(command, COMMANDS, n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        raise SystemExit(f"umrl: got command {command!r}{hint}; expected one of {', '.join(COMMANDS)}\n\n{usage()}")
    sys.argv = [f"umrl {command}", *rest]
    run(command)


def run(command: str) -> None:
    """Run ``command``'s Hydra app on the arguments in ``sys.argv[1:]``: its per-env defaults chosen from
    ``env.name`` (:func:`~umrl.configs.env_groups.with_env_group_argv`), its ``--help`` text registered, its
    overrides' keys checked against its config (:func:`~umrl.cli.errors.unknown_key_errors`), then its ``main``."""
    # imported here: `umrl --help` and a misspelt command answer without loading torch
    from umrl.cli.errors import full_error_requested, unknown_key_errors
    from umrl.configs import ConfigError
    from umrl.configs.env_groups import with_env_group_argv
    from umrl.trainers.config import register_help_text

    try:  # env.name=X chooses the recipe's per-env defaults (umrl/configs/<recipe>_env/X.yaml)
        sys.argv[1:] = with_env_group_argv(command, sys.argv[1:])
    except ValueError as e:
        raise SystemExit(f"umrl {command}: {e}") from None
    app = importlib.import_module(f"umrl.cli.{command}")
    register_help_text(app.CONFIG_DIR)
    if not full_error_requested():  # else Hydra raises the composition error with its traceback
        errors = unknown_key_errors(app.CONFIG_DIR, app.CONFIG_NAME, sys.argv[1:])
        if errors:
            raise SystemExit(str(ConfigError(command, errors)))
    app.main()
