"""Keep MuJoCo's warnings on the console but out of ``MUJOCO_LOG.TXT`` in the working directory.

MuJoCo's default log handler appends every warning (model compiler deprecations, unstable-simulation warnings) to
``MUJOCO_LOG.TXT`` in the current directory. :func:`disable_mujoco_log_file` turns that file off through MuJoCo's
own handler configuration (``mju_setLogConfig``) and leaves console output as it is. The setting is process-wide;
umrl's MuJoCo env modules apply it when imported.
"""

from __future__ import annotations

import mujoco


def disable_mujoco_log_file() -> None:
    """Stop MuJoCo's default log handler from writing ``MUJOCO_LOG.TXT`` (console messages are kept)."""
    config = mujoco.MjLogConfig.get()
    config.logto_file = False
    config.set()
