"""The ``umrl`` command line (umrl.cli): one command per recipe and the suite, bad input refused with the clear
lines only (the key, the value, what is accepted; "did you mean" for a misspelt key), tracebacks behind
HYDRA_FULL_ERROR=1."""
import os
import re
import subprocess
import sys

import pytest
from omegaconf import OmegaConf

import umrl.cli
from umrl.cli.errors import refuses_bad_config, unknown_key_errors
from umrl.configs import ConfigError
from umrl.suite import CONFIG_DIR as SUITE_CONFIG_DIR
from umrl.trainers import CONFIG_DIR


def test_a_misspelt_key_gets_the_closest_key_and_every_unknown_key_is_listed():
    lines = unknown_key_errors(CONFIG_DIR, "maml", ["+profile=maml_tiny", "maml.inner_lrr=0.1", "inner_lr=0.5",
                                                    "mmal.inner_lr=2", "policy.nope=1", "seed=3"])
    assert lines == [
        "maml.inner_lrr: got 0.1; expected a key of the maml config (did you mean maml.inner_lr?)",
        "inner_lr: got 0.5; expected a key of the maml config (did you mean maml.inner_lr?)",
        "mmal.inner_lr: got 2; expected a key of the maml config (did you mean maml.inner_lr?)",
        "policy.nope: got 1; expected a key of the maml config (one of policy.hidden, policy.init_std, policy.learn_std)",
    ]


def test_a_renamed_key_is_answered_with_its_new_name():
    assert unknown_key_errors(CONFIG_DIR, "vime", ["trpo.gae_lambda=0.9", "trpo.gamma=0.5"]) == [
        "trpo.gae_lambda: got 0.9; expected advantage.lmbda (the key's new name)",
        "trpo.gamma: got 0.5; expected advantage.gamma (the key's new name)",
    ]


def test_known_keys_sweeps_flags_and_hydra_keys_pass_the_key_check():
    args = ["-m", "seed=0,1", "+profile=maml_tiny", "maml.inner_lr=0.1,0.5", "hydra.sweep.dir=/tmp/x", "--cfg", "job"]
    assert unknown_key_errors(CONFIG_DIR, "maml", args) == []
    assert unknown_key_errors(SUITE_CONFIG_DIR, "suite", ["profile=tiny", "launcher.workers=0"]) == []
    assert unknown_key_errors(SUITE_CONFIG_DIR, "suite", ["launcher.worker=0"]) == [
        "launcher.worker: got 0; expected a key of the suite config (did you mean launcher.workers?)"]
    assert unknown_key_errors(CONFIG_DIR, "maml", ["+profile=no_such_profile", "seed=[1"]) == []  # Hydra says why


def test_a_config_error_ends_the_command_with_its_lines_unless_the_full_error_is_asked_for(monkeypatch):
    error = ConfigError("MAMLConfig", ["maml.inner_lr: got -1; expected a finite number > 0"])

    @refuses_bad_config
    def main(cfg):
        raise error

    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    with pytest.raises(SystemExit, match="maml.inner_lr: got -1; expected a finite number > 0") as exit_info:
        main(OmegaConf.create({}))
    assert exit_info.value.__cause__ is None and exit_info.value.__suppress_context__
    monkeypatch.setenv("HYDRA_FULL_ERROR", "1")
    with pytest.raises(ConfigError):
        main(OmegaConf.create({}))


def test_commands_usage_and_a_misspelt_command(capsys):
    umrl.cli.main([])
    usage = capsys.readouterr().out
    assert all(f"\n  {name} " in usage for name in umrl.cli.COMMANDS)
    with pytest.raises(SystemExit, match="umrl: got command 'mmal' \\(did you mean maml\\?\\); expected one of diayn"):
        umrl.cli.main(["mmal", "seed=1"])


def test_an_unknown_key_is_refused_before_hydra_starts(monkeypatch, tmp_path):
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    monkeypatch.setattr(sys, "argv", ["umrl suite", "profile=tiny", "envz=[ant]", f"output_dir={tmp_path}"])
    message = ("invalid config (suite, 1 error):\n  envz: got [ant]; expected a key of the suite config "
               "(did you mean envs?)")
    with pytest.raises(SystemExit, match=re.escape(message)):
        umrl.cli.run("suite")
    assert not (tmp_path / "hydra").exists()


def test_a_bad_value_prints_the_line_without_a_traceback(tmp_path):
    """The whole path through Hydra: the job's ConfigError becomes its lines and exit status 1."""
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    proc = subprocess.run([sys.executable, "-m", "umrl", "maml", "maml.inner_lr=-1", "logger.backend=none",
                           f"output_dir={tmp_path}"], check=False, capture_output=True, text=True, timeout=300,
                          cwd=tmp_path, env=env)
    assert proc.returncode == 1
    assert proc.stderr.strip() == ("invalid config (MAMLConfig, 1 error):\n"
                                   "  maml.inner_lr: got -1; expected a finite number > 0")
    assert (tmp_path / "hydra" / "maml.log").is_file()  # Hydra names the job after its command


def test_a_sweep_keeps_every_jobs_run(tmp_path):
    """``-m`` over a key ``output_dir`` does not name: each job runs in ``<output_dir>/<key=value>``; a key it names
    (``seed`` in the default folder) keeps its folder."""
    common = ["+profile=maml_tiny", "iterations=1", "meta_batch_size=2", "trajectories_per_task=2", "env.horizon=5",
              "logger.backend=none", "progress=false", f"hydra.sweep.dir={tmp_path / 'multirun'}"]
    out = subprocess.run([sys.executable, "-m", "umrl", "maml", "-m", *common, "maml.inner_lr=0.1,0.5",
                          f"output_dir={tmp_path / 'sweep'}"], capture_output=True, text=True, timeout=600, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    for lr in ("0.1", "0.5"):
        assert (tmp_path / "sweep" / f"maml.inner_lr={lr}" / "checkpoints" / "step_1.safetensors").is_file()
    out = subprocess.run([sys.executable, "-m", "umrl", "maml", "-m", *common, "seed=0,1",
                          f"output_dir={tmp_path}/seeds/seed${{seed}}"], capture_output=True, text=True,
                         timeout=600, check=False)
    assert out.returncode == 0, out.stderr[-2000:]
    assert sorted(p.name for p in (tmp_path / "seeds").iterdir()) == ["seed0", "seed1"]
