"""Runs used where they do not fit: a resume with a budget already spent, an unreadable newest checkpoint, reused
runs the suite would train around or whose skill count an override contradicts, a checkpoint of another proposal or
env meta-tested; each refused before any work in the house format, or handled (the unreadable file set aside)."""
import importlib
import warnings
from pathlib import Path

import pytest
import torch
from test_names import _maml_run, _suite
from test_resume import BUDGET, config

from umrl import checkpoints
from umrl.checkpoints import DIAYN_FORMAT, VIME_FORMAT
from umrl.checkpoints.diayn import DIAYN_SEEDS_FORMAT
from umrl.checkpoints.file import read_checkpoint
from umrl.checkpoints.folder import Checkpointer
from umrl.configs import ConfigError
from umrl.envs import get_env_spec
from umrl.metatest import CellSpec, run_cell
from umrl.suite import plan, plan_pretraining
from umrl.validation import InvalidValue

UNITS = {"diayn": "frames", "maml": "iterations", "vime": "iterations"}
POLICY = {"diayn": "actor", "maml": "policy", "vime": "policy"}
"""Each recipe's checkpoint entry holding the policy its loader returns."""
LOAD_POLICY = {"diayn": lambda path: checkpoints.load_skill_policy(path)[0],
               "maml": lambda path: checkpoints.load_maml_policy(path)[0], "vime": checkpoints.load_vime_policy}


@pytest.fixture(scope="module", params=["diayn", "maml", "vime"])
def resumed_past_garbage(request, tmp_path_factory):
    """``(recipe, run_dir, result, warnings)``: a tiny point_nav run stopped half-way, given a garbage newest
    ``step_99999.pt`` and resumed to its end (every checkpoint kept)."""
    recipe, run_dir = request.param, tmp_path_factory.mktemp(request.param)
    train = importlib.import_module(f"umrl.trainers.{recipe}").train
    key, stop, end = BUDGET[recipe]
    train(config(recipe, run_dir, "point_nav", f"{key}={stop}", "checkpoint.keep_all=true"))
    (run_dir / "checkpoints" / "step_99999.pt").write_bytes(b"not a checkpoint")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = train(config(recipe, run_dir, "point_nav", f"{key}={end}", "checkpoint.keep_all=true", "resume=true"))
    return recipe, run_dir, result, [str(w.message) for w in caught]


def test_a_resume_sets_an_unreadable_newest_checkpoint_aside_so_loaders_read_the_resumed_run(resumed_past_garbage):
    recipe, run_dir, result, messages = resumed_past_garbage
    bad = run_dir / "checkpoints" / "step_99999.pt"
    assert any(f"moved the unreadable checkpoint {bad} aside to step_99999.pt.unreadable" in m for m in messages)
    assert not bad.exists() and bad.with_name("step_99999.pt.unreadable").exists()
    assert Checkpointer(run_dir / "checkpoints").latest() == Path(result["checkpoint"])
    policy = LOAD_POLICY[recipe](run_dir)  # the run directory: its newest checkpoint, the resumed run's last
    newest = Checkpointer(Path(result["runs"][0]) / "checkpoints").latest() if recipe == "diayn" else result["checkpoint"]
    saved = read_checkpoint(newest)[POLICY[recipe]]  # DIAYN: the seed's skills, beside the program's checkpoint
    assert all(torch.equal(value, saved[name]) for name, value in policy.state_dict().items())


def test_a_resume_with_a_budget_already_done_is_refused_naming_the_key(resumed_past_garbage):
    recipe, run_dir, _, _ = resumed_past_garbage
    train = importlib.import_module(f"umrl.trainers.{recipe}").train
    key, stop, end = BUDGET[recipe]
    for budget in (stop, end):
        with pytest.raises(InvalidValue, match=rf"^{key}: got {budget} \(nothing to do: the run in {run_dir} has "
                                               rf"already done {end} {UNITS[recipe]}\); expected > {end} to continue "
                                               "it with resume=true$"):
            train(config(recipe, run_dir, "point_nav", f"{key}={budget}", "checkpoint.keep_all=true", "resume=true"))


def _diayn_run(directory, num_skills=50, env="point_nav"):
    meta = {**dict.fromkeys(DIAYN_FORMAT.meta_keys), "env": env, "num_skills": num_skills,
            "obs_dim": get_env_spec(env).obs_dim}
    DIAYN_FORMAT.save(Checkpointer(directory / "checkpoints"), 5, meta, {"seed": 0})


def test_a_diayn_run_only_reused_uml_diayn_runs_would_read_is_not_trained(tmp_path):
    _maml_run(tmp_path / "uml", proposal="diayn")
    reuse = f"pretrain.maml.reuse='{tmp_path}/uml'"
    cfg = _suite(tmp_path / "out", "methods=[uml_diayn]", reuse)
    runs = plan_pretraining(cfg, "g", "code")
    assert list(runs) == [("maml_diayn", "point_nav", 0)]
    assert not [job.key for job in plan(cfg, "g", "code", runs) if job.key.startswith("pretrain/diayn")]
    cfg = _suite(tmp_path / "out", "methods=[uml_diayn,diayn_init]", reuse)  # DIAYN-init starts from it: trained
    jobs = {job.key: job for job in plan(cfg, "g", "code")}
    assert not jobs["pretrain/maml_diayn/point_nav/seed0"].deps and "pretrain/diayn/point_nav/seed0" in jobs


def test_a_skill_count_override_a_reused_run_was_not_trained_with_is_refused(tmp_path):
    _diayn_run(tmp_path / "diayn", num_skills=50)
    _maml_run(tmp_path / "uml", proposal="diayn", num_skills=20)
    _maml_run(tmp_path / "random", proposal="random", num_skills=20)
    diayn, uml = f"pretrain.diayn.reuse='{tmp_path}/diayn'", f"pretrain.maml.reuse='{tmp_path}/uml'"
    for overrides, message in (
        ([diayn, "methods=[diayn_init]", "+pretrain.diayn.overrides.num_skills=3"],
         (rf"pretrain.diayn.overrides.num_skills: got 3 \(the reused diayn run in {tmp_path}/diayn "
          r"\(pretrain.diayn.reuse\) has 50 skills and is used as it is\); expected 50 or no override")),
        ([uml, "methods=[uml_diayn,diayn_init]", "+pretrain.diayn.overrides.num_skills=3"],  # DIAYN trained on 3
         (rf"pretrain.diayn.overrides.num_skills: got 3 \(the reused maml_diayn run in {tmp_path}/uml "
          r"\(pretrain.maml.reuse\) has 20 skills")),
        ([f"pretrain.maml.reuse='{tmp_path}/random'", "methods=[uml_random]", "+pretrain.maml.overrides.num_skills=3"],
         r"pretrain.maml.overrides.num_skills: got 3 \(the reused maml_random run .* has 20 skills"),
    ):
        with pytest.raises(ConfigError, match=message):
            plan_pretraining(_suite(tmp_path / "out", *overrides), "g", "code")
    plan_pretraining(_suite(tmp_path / "out", diayn, "methods=[diayn_init]", "+pretrain.diayn.overrides.num_skills=50"),
                     "g", "code")  # the count it was trained with


@pytest.mark.parametrize(("method", "make_run", "found", "expected"), [
    ("uml_diayn", lambda d: _maml_run(d, proposal="oracle"), "env='point_nav', proposal='oracle'",
     "a MAML run with env='point_nav', proposal='diayn'"),
    ("uml_random", lambda d: _maml_run(d, env="half_cheetah", proposal="random"),
     "env='half_cheetah', proposal='random'", "a MAML run with env='point_nav', proposal='random'"),
    ("diayn_init", lambda d: _diayn_run(d, env="half_cheetah"), "env='half_cheetah'", "a DIAYN run with env='point_nav'"),
    ("vime_init", lambda d: VIME_FORMAT.save(
        Checkpointer(d / "checkpoints"), 1, {**dict.fromkeys(VIME_FORMAT.meta_keys), "env": "ant", "obs_dim": 105},
        {"seed": 0}), "env='ant'", "a VIME run with env='point_nav'"),
])
def test_a_checkpoint_of_another_proposal_or_env_is_refused_before_meta_test(tmp_path, method, make_run, found,
                                                                            expected):
    make_run(tmp_path / "run")
    spec = CellSpec(method=method, env="point_nav", seed=0, output=str(tmp_path / "cell.csv"),
                    checkpoint=str(tmp_path / "run"), num_tasks=2)
    with pytest.raises(InvalidValue, match=rf"^checkpoint: got '{tmp_path}/run' \(a \w+ run with {found}\); "
                                           rf"expected {expected} \(method '{method}' on point_nav\)$"):
        run_cell(spec)
    assert not list(tmp_path.glob("cell.*"))


def test_a_reused_one_seed_diayn_run_is_read_from_its_seed_folder(tmp_path):
    """A one-seed run's output_dir holds the program's state (``checkpoints/``) beside the seed's skills
    (``seed0/``): the suite's reuse check and every DIAYN loader read the skills."""
    _diayn_run(tmp_path / "diayn" / "seed0", num_skills=50)
    meta = {**dict.fromkeys(DIAYN_SEEDS_FORMAT.meta_keys), "env": "point_nav", "num_skills": 50, "obs_dim": 2,
            "seeds": [0]}
    DIAYN_SEEDS_FORMAT.save(Checkpointer(tmp_path / "diayn" / "checkpoints"), 5, meta, {"seed": 0})
    assert DIAYN_FORMAT.load(tmp_path / "diayn")["format"] == DIAYN_FORMAT.name
    with pytest.raises(ConfigError, match=r"pretrain.diayn.overrides.num_skills: got 3 \(the reused diayn run .* "
                                          r"has 50 skills"):
        plan_pretraining(_suite(tmp_path / "out", f"pretrain.diayn.reuse='{tmp_path}/diayn'", "methods=[diayn_init]",
                                "+pretrain.diayn.overrides.num_skills=3"), "g", "code")
