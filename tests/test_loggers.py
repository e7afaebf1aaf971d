"""Loggers (:mod:`umrl.loggers`): backends, where their files go."""
import os

import pytest

from umrl.loggers import close_logger, log_metrics, make_logger


def test_csv_logger_writes_scalars(tmp_path):
    logger = make_logger({"backend": "csv"}, exp_name="exp", config={"lr": 0.1}, log_dir=tmp_path)
    log_metrics(logger, {"train/x": 1.5}, step=3)
    files = list((tmp_path / "csv").rglob("*.csv"))
    assert any("1.5" in f.read_text() for f in files)
    assert make_logger({"backend": "none"}, exp_name="exp") is None
    with pytest.raises(ValueError, match="valid choices"):
        make_logger({"backend": "tensorboardx"}, exp_name="exp")


def test_wandb_defaults_to_an_offline_run(tmp_path, monkeypatch):
    monkeypatch.delenv("WANDB_MODE", raising=False)
    monkeypatch.setenv("WANDB_DIR", str(tmp_path))
    logger = make_logger({"backend": "wandb", "group": "g"}, exp_name="exp", config={"lr": 0.1})
    log_metrics(logger, {"train/x": 1.0}, step=0)
    assert logger.experiment.settings.mode == "offline" and logger.experiment.group == "g"
    assert "WANDB_MODE" not in os.environ  # the mode is this run's, not the process's (a later job may be online)
    close_logger(logger)
    assert list((tmp_path / "wandb").glob("offline-run-*"))


def test_wandb_runs_land_under_the_output_dir(tmp_path, monkeypatch):
    monkeypatch.delenv("WANDB_DIR", raising=False)
    seen = {}
    monkeypatch.setattr("umrl.loggers.get_logger", lambda backend, **kwargs: seen.update(kwargs))
    make_logger({"backend": "wandb"}, exp_name="exp", log_dir=tmp_path / "run")
    assert seen["logger_name"] == str(tmp_path / "run") and (tmp_path / "run").is_dir()  # -> <output_dir>/wandb
    monkeypatch.setenv("WANDB_DIR", str(tmp_path / "elsewhere"))
    make_logger({"backend": "wandb"}, exp_name="exp", log_dir=tmp_path / "run")
    assert seen["logger_name"] == str(tmp_path / "elsewhere")
