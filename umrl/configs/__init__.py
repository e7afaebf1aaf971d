"""Typed, validated configs: one schema per recipe (``umrl.configs.diayn`` / ``maml`` / ``vime``) and the suite
(``umrl.configs.suite``), checked by :func:`validate` before any work starts; :func:`resume_diff` /
:func:`check_resume` compare a resumed run's config with its checkpoint's.
"""
from umrl.configs.validate import RESUME_ALLOW, ConfigError, check_resume, resume_diff, validate

__all__ = ["RESUME_ALLOW", "ConfigError", "check_resume", "resume_diff", "validate"]
