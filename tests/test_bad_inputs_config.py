"""Config values refused (or warned about) before any work starts, naming the key, the value and what is accepted:
seeds beyond int64, sizes the machine's memory cannot hold, DIAYN's entropy scale and torch.compile on a CPU, an
output_dir that cannot be written, a malformed Ray address, a DIAYN budget the collector rounds up, and MAML's
num_skills with a proposal that ignores it."""
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf
from script_loading import repo_env

import umrl.configs.memory
from umrl.configs import ConfigError, validate
from umrl.configs.callbacks import OutputDirCheck
from umrl.configs.diayn import DIAYNConfig
from umrl.configs.maml import MAMLConfig
from umrl.configs.memory import Allocation, allocation_errors, format_bytes
from umrl.configs.suite import SuiteConfig
from umrl.configs.vime import VIMEConfig
from umrl.trainers import compose
from umrl.trainers.config import config_dir
from umrl.validation import SEED_MAX, InvalidValue, check_writable_dir

REPO = Path(__file__).resolve().parents[1]
SCHEMAS = {"diayn": DIAYNConfig, "maml": MAMLConfig, "vime": VIMEConfig}
GIB = 2**30


def suite(overrides=()):
    from hydra import compose as hydra_compose

    with config_dir(REPO / "umrl" / "suite" / "config"):
        return hydra_compose("suite", overrides=list(overrides))


def errors(name, overrides, schema=None):
    """The error lines of validating recipe ``name`` (or the suite) with ``overrides``."""
    cfg = suite(overrides) if name == "suite" else compose(name, overrides)
    with pytest.raises(ConfigError) as info:
        validate(cfg, schema or SuiteConfig)
    return info.value.errors


def one_error(name, overrides, start):
    lines = errors(name, overrides, SCHEMAS.get(name))
    found = [e for e in lines if e.startswith(start)]
    assert found, lines
    return found[0]


# --- seeds -----------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["diayn", "maml", "vime"])
def test_a_seed_beyond_int64_is_refused_with_the_range(name):
    one_error(name, ["seed=99999999999999999999"],
              "seed: got 99999999999999999999; expected an integer in [0, 9223372036854775807]")


def test_the_largest_seed_is_accepted():
    assert validate(compose("maml", [f"seed={SEED_MAX}"]), MAMLConfig).seed == SEED_MAX == 2**63 - 1


@pytest.mark.parametrize("overrides, start", [
    (["seeds=[0,99999999999999999999]"], "seeds[1]: got 99999999999999999999; expected an integer in [0, 9223372036854775807]"),
    (["pretrain_seeds=99999999999999999999"], "pretrain_seeds: got 99999999999999999999; expected an integer in [0, "),
    (["ablation.seeds=[99999999999999999999]"], "ablation.seeds[0]: got 99999999999999999999; expected an integer in [0, "),
])
def test_suite_seeds_beyond_int64_are_refused(overrides, start):
    lines = errors("suite", overrides)
    assert any(e.startswith(start) for e in lines), lines


# --- memory preflight ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name, overrides, start", [
    ("diayn", ["replay_buffer.size=100000000000"], "replay_buffer.size: got 100000000000 (≈ "),
    ("maml", ["trajectories_per_task=1000000000000"], "trajectories_per_task: got 1000000000000 (≈ "),
    ("vime", ["dynamics.replay_size=100000000000"], "dynamics.replay_size: got 100000000000 (≈ "),
    ("vime", ["env.num_envs=10000000000"], "env.num_envs: got 10000000000 (≈ "),
])
def test_sizes_no_machine_can_hold_are_refused_before_any_allocation(name, overrides, start):
    line = one_error(name, overrides, start)
    assert "; expected at most " in line and "on this machine (" in line and "available)" in line


def test_a_suite_meta_test_batch_no_machine_can_hold_is_refused():
    lines = errors("suite", ["protocol.num_trajectories=1000000000000"])
    assert any(e.startswith("protocol.num_trajectories: got 1000000000000 (≈ ") and "expected at most" in e
               for e in lines), lines


def test_the_memory_message_gives_the_estimate_and_the_most_that_fits(monkeypatch):
    monkeypatch.setattr(umrl.configs.memory, "available_memory", lambda device: 8 * GIB)
    # point_nav transition: 2 x 2 observation floats, 2 action floats, 2 x 5 skill floats = 16 floats = 64 bytes
    line = one_error("diayn", ["num_skills=5", "collector.frames_per_batch=1600", "replay_buffer.size=200000000"],
                     "replay_buffer.size")
    assert line == ("replay_buffer.size: got 200000000 (≈ 11.92 GiB of replay buffer); expected at most 134216128 with "
                    "env.name=point_nav, 5 skills and 1 seed(s) on this machine (8 GiB available)")


def test_the_memory_preflight_counts_every_seeds_replay(monkeypatch):
    """Three seeds hold three replays: a size that fits one seed's is refused for three, with the most that fits."""
    monkeypatch.setattr(umrl.configs.memory, "available_memory", lambda device: 8 * GIB)
    line = one_error("diayn", ["num_skills=5", "seeds=[0,1,2]", "replay_buffer.size=100000000"], "replay_buffer.size")
    assert line.startswith("replay_buffer.size: got 100000000 (≈ 17.88 GiB of replay buffer); expected at most "
                           "44739241 with env.name=point_nav, 5 skills and 3 seed(s) on this machine (8 GiB available)")


def test_allocations_that_fit_alone_but_not_together_name_the_others(monkeypatch):
    monkeypatch.setattr(umrl.configs.memory, "available_memory", lambda device: 1000)
    line, = allocation_errors([Allocation("a", 60, 10, "as"), Allocation("b", 50, 10, "bs", "with c=1")], "cpu")
    assert line == "a: got 60 (≈ 600 B of as, 1.074 KiB with b); expected at most 50 on this machine (1000 B available)"


def test_no_memory_figure_means_no_refusal(monkeypatch):
    monkeypatch.setattr(umrl.configs.memory, "available_memory", lambda device: None)
    assert allocation_errors([Allocation("a", 10**15, 10**6, "as")], "cpu") == []


@pytest.mark.parametrize("name, overrides", [
    ("diayn", ["env.name=ant"]),  # the reference's 10^6-transition replay on the largest observation
    ("maml", ["env.name=ant", "env.horizon=200", "trajectories_per_task=40"]),
    ("vime", ["env.name=ant"]),
])
def test_the_reference_settings_fit_in_2_gib(monkeypatch, name, overrides):
    monkeypatch.setattr(umrl.configs.memory, "available_memory", lambda device: 2 * GIB)
    validate(compose(name, overrides), SCHEMAS[name])


def test_on_a_gpu_its_free_memory_counts(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda: (4 * GIB, 141 * GIB))
    line, = allocation_errors([Allocation("replay_buffer.size", 10**9, 64, "replay buffer")], "cuda")
    assert line.endswith("expected at most 67108864 on this machine (4 GiB free on the GPU)")


def test_format_bytes():
    assert [format_bytes(n) for n in (512, 1536, 12 * 2**40)] == ["512 B", "1.5 KiB", "12 TiB"]


# --- DIAYN's alpha and torch.compile ---------------------------------------------------------------------------------


def test_a_zero_entropy_scale_is_refused_by_its_key():
    one_error("diayn", ["optim.alpha=0"], "optim.alpha: got 0; expected a finite number > 0")


def test_torch_compile_is_accepted_on_a_cpu_and_on_a_gpu(monkeypatch):
    """On a CPU it compiles the hand-derived gradients (StackedDIAYNUpdate), on a GPU the whole update."""
    assert validate(compose("diayn", ["device=cpu", "optim.compile=true"]), DIAYNConfig).optim.compile
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "mem_get_info", lambda: (100 * GIB, 141 * GIB))
    assert validate(compose("diayn", ["device=cuda", "optim.compile=true"]), DIAYNConfig).optim.compile


def test_torch_compile_in_the_suites_diayn_overrides_is_accepted_on_a_cpu():
    assert validate(suite(["+pretrain.diayn.overrides.optim.compile=true"]), SuiteConfig)


# --- output_dir ------------------------------------------------------------------------------------------------------


def test_an_output_dir_that_is_a_file_is_refused(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("")
    one_error("vime", [f"output_dir={afile}"], f"output_dir: got '{afile}' (a file); expected a writable directory")
    one_error("diayn", [f"output_dir={afile / 'run'}"],
              f"output_dir: got '{afile / 'run'}' ({afile} is a file); expected a writable directory")
    lines = errors("suite", [f"output_dir={afile}"])
    assert f"output_dir: got '{afile}' (a file); expected a writable directory" in lines


def test_an_output_dir_in_a_read_only_directory_is_refused(tmp_path, monkeypatch):
    monkeypatch.setattr(os, "access", lambda path, mode: Path(path) != tmp_path)  # root may write anywhere
    message = f"output_dir: got '{tmp_path / 'run'}' ({tmp_path} is not writable); expected a writable directory"
    with pytest.raises(InvalidValue, match=re.escape(message)):
        check_writable_dir("output_dir", str(tmp_path / "run"))


def test_a_writable_output_dir_is_accepted_and_not_created(tmp_path):
    assert check_writable_dir("output_dir", str(tmp_path / "a" / "b")) == str(tmp_path / "a" / "b")
    assert not (tmp_path / "a").exists()


def test_the_command_line_refuses_a_bad_output_dir_before_hydra_writes(tmp_path):
    afile = tmp_path / "afile"
    afile.write_text("")
    config = OmegaConf.create({"output_dir": str(afile), "hydra": {"run": {"dir": "${output_dir}/hydra"}}})
    message = f"invalid config (vime, 1 error):\n  output_dir: got '{afile}' (a file); expected a writable directory"
    with pytest.raises(SystemExit, match=re.escape(message)):
        OutputDirCheck().on_run_start(config=config, config_name="vime")
    proc = subprocess.run([sys.executable, str(REPO / "recipes" / "vime.py"), f"output_dir={afile / 'run'}"],
                          check=False, capture_output=True, text=True, timeout=120, cwd=tmp_path,
                          env=repo_env(HYDRA_FULL_ERROR="0"))
    assert proc.returncode == 1
    assert f"output_dir: got '{afile / 'run'}' ({afile} is a file); expected a writable directory" in proc.stderr
    assert "NotADirectoryError" not in proc.stderr


# --- Ray address -----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("address", ["foo", "host:0", "host:99999", "ray://host", "http://host:8265", ":6379"])
def test_a_malformed_ray_address_is_refused(address):
    lines = errors("suite", [f"launcher.ray_address='{address}'"])
    assert (f"launcher.ray_address: got '{address}'; expected null or 'auto', 'local', host:port or ray://host:port "
            "(port 1-65535)") in lines


@pytest.mark.parametrize("address", ["auto", "local", "10.0.0.1:6379", "head-node:6379", "ray://1.2.3.4:10001",
                                     "[::1]:6379"])
def test_ray_addresses_ray_init_takes_are_accepted(address):
    assert validate(suite([f"launcher.ray_address='{address}'"]), SuiteConfig).launcher.ray_address == address


# --- DIAYN's budget --------------------------------------------------------------------------------------------------

TINY_DIAYN = ["collector.init_random_frames=0", "collector.frames_per_batch=400", "replay_buffer.batch_size=32",
              "env.num_envs=4", "env.horizon=100"]


def test_a_budget_the_collector_rounds_up_is_warned_with_both_numbers():
    with pytest.warns(UserWarning, match=r"collector.total_frames: got 100 \(the collector runs whole batches: 400 "
                                         r"frames will run\); expected a multiple of collector.frames_per_batch \(400\)"):
        validate(compose("diayn", [*TINY_DIAYN, "collector.total_frames=100"]), DIAYNConfig)


def test_a_whole_number_of_batches_is_not_warned(recwarn):
    validate(compose("diayn", [*TINY_DIAYN, "collector.total_frames=800"]), DIAYNConfig)
    assert not [w for w in recwarn if "collector.total_frames" in str(w.message)]


# --- MAML's num_skills -----------------------------------------------------------------------------------------------


def test_num_skills_with_the_diayn_proposal_is_refused(tiny_diayn_checkpoint):
    directory, _ = tiny_diayn_checkpoint
    assert errors("maml", ["proposal=diayn", f"diayn_checkpoint={directory}", "num_skills=7"], MAMLConfig) == [
        "num_skills: got 7; expected null with proposal=diayn (the skill count comes from the DIAYN checkpoint)"]
    validate(compose("maml", ["+profile=maml_tiny", "proposal=diayn", f"diayn_checkpoint={directory}"]), MAMLConfig)


def test_num_skills_with_the_oracle_proposal_is_refused():
    one_error("maml", ["proposal=oracle", "num_skills=7"], "num_skills: got 7; expected null with proposal=oracle (")
    validate(compose("maml", ["+profile=maml_tiny"]), MAMLConfig)  # the default proposal: the profile still runs


@pytest.mark.parametrize("proposal", ["random", "random_arena"])
def test_num_skills_with_a_random_proposal_is_accepted(proposal):
    assert validate(compose("maml", [f"proposal={proposal}", "num_skills=7"]), MAMLConfig).num_skills == 7


def test_the_suites_maml_num_skills_is_refused_when_a_diayn_or_oracle_run_would_take_it():
    lines = errors("suite", ["+pretrain.maml.overrides.num_skills=3"])
    assert ("pretrain.maml.overrides.num_skills: got 3; expected null with proposal=diayn (the skill count comes from "
            "the DIAYN checkpoint)") in lines
    assert any(e.startswith("pretrain.maml.overrides.num_skills: got 3; expected null with proposal=oracle") for e in lines)
    cfg = validate(suite(["+pretrain.maml.overrides.num_skills=3", "methods=[uml_random,scratch]",
                          "ablation.enabled=false"]), SuiteConfig)
    assert cfg.pretrain.maml.overrides.num_skills == 3
