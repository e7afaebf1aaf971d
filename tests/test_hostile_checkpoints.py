"""Hostile but hash-valid checkpoint files: the hash is an integrity check that whoever writes a file can recompute,
so every malformed, special or tampered file must raise the one ``CheckpointError`` naming it, before anything large
is allocated, and a resume must fall back to the previous checkpoint."""
import json
import math
import os
import resource
import signal

import pytest
import safetensors.torch
import torch

import umrl.checkpoints.diayn
import umrl.checkpoints.maml
import umrl.checkpoints.vime
from umrl import checkpoints
from umrl.checkpoints import DIAYN_FORMAT, MAML_FORMAT, VIME_FORMAT
from umrl.checkpoints.diayn import DIAYN_SEEDS_FORMAT
from umrl.checkpoints.file import (
    FILE_FORMAT,
    CheckpointError,
    content_hash,
    read_checkpoint,
    write_checkpoint,
)
from umrl.checkpoints.folder import Checkpointer
from umrl.checkpoints.format import MAX_LAYERS, MAX_WIDTH
from umrl.modules import make_discriminator, make_gaussian_policy, make_skill_actor
from umrl.modules.bnn import BayesianDynamics


def write_tree(path, tree_json, tensors=None):
    """A file in umrl's container with any JSON tree and a valid hash: what anyone who can write the file can make."""
    tensors = tensors or {"t0": torch.zeros(3)}
    safetensors.torch.save_file(tensors, str(path), metadata={
        "format": FILE_FORMAT, "tree": tree_json, "sha256": content_hash(tree_json, tensors)})
    return path


MALFORMED_TREES = {
    "a JSON tree nested 100,000 deep": ("[" * 100_000 + "]" * 100_000, "RecursionError"),
    "a TensorDict whose batch size its tensors lack": (
        json.dumps({"__tensordict__": {"x": {"__tensor__": "t0"}}, "batch_size": [7]}), "batch dimension mismatch"),
    "a negative TensorDict batch size": (json.dumps({"__tensordict__": {}, "batch_size": [-1]}), "not a tensor dim"),
    "an object array": (json.dumps({"__ndarray__": "t0", "dtype": "O"}), "dtype 'O' is not numeric"),
    "a string dtype of 400 MB per element": (json.dumps({"__ndarray__": "t0", "dtype": "<U100000000"}),
                                             "is not numeric"),
    "a tuple tag holding a number": (json.dumps({"__tuple__": 5}), "TypeError"),
    "an unhashable dict key": (json.dumps({"__dict__": [[[1], 2]]}), "unhashable"),
    "a size beyond int64": (json.dumps({"__size__": [10**30]}), "not a tensor dimension"),
    "an integer of 5,000 digits": ("1" + "0" * 5000, "digits"),
    "a numpy scalar of text": (json.dumps({"__npscalar__": "x", "dtype": "<f8"}), "could not convert"),
    "an unknown torch dtype": (json.dumps({"__dtype__": "Tensor"}), "unknown torch dtype"),
}


@pytest.mark.parametrize("label", list(MALFORMED_TREES))
def test_a_malformed_hash_valid_tree_is_the_checkpoint_error_naming_the_file(tmp_path, label):
    tree_json, why = MALFORMED_TREES[label]
    path = write_tree(tmp_path / "step_1.pt", tree_json)
    with pytest.raises(CheckpointError, match=rf"cannot read checkpoint {path} \(\d+ bytes\): .*{why}"):
        read_checkpoint(path)


def _fifo(path):
    os.mkfifo(path)


def _zeros(path):
    path.symlink_to("/dev/zero")


SPECIAL = {"a FIFO": _fifo, "a folder": os.mkdir, "a symlink to /dev/zero": _zeros}


@pytest.mark.parametrize("kind", list(SPECIAL))
def test_a_special_file_is_refused_before_a_byte_is_read(tmp_path, kind):
    path = tmp_path / "step_5.pt"
    SPECIAL[kind](path)
    signal.alarm(10)  # a FIFO read blocks and /dev/zero never ends: fail instead of hanging the suite
    try:
        with pytest.raises(CheckpointError, match=rf"cannot read checkpoint {path} \(a .*\): not a regular file"):
            read_checkpoint(path)
    finally:
        signal.alarm(0)


def test_an_unreadable_file_is_the_checkpoint_error(tmp_path):
    if os.geteuid() == 0:
        pytest.skip("root reads files without read permission")
    path = write_tree(tmp_path / "step_1.pt", "1")
    path.chmod(0)
    with pytest.raises(CheckpointError, match=rf"cannot read checkpoint {path} \(not opened\): Permission denied"):
        read_checkpoint(path)


# ---- each format's content: finite numbers, sizes its tensors have, networks that load -------------------------

def _diayn(hidden=(16,)):
    meta = {"env": "point_nav", "obs_dim": 2, "act_dim": 2, "num_skills": 4, "hidden": list(hidden),
            "discriminator_hidden": [16], "discriminator_observation_key": ["observation"],
            "discriminator_input_dims": None}
    return meta, {"actor": make_skill_actor(2, 4, 2, hidden=hidden).state_dict(),
                  "discriminator": make_discriminator(2, 4, hidden=(16,)).state_dict(), "counters": {"frames": 1}}


def _maml(hidden=(16,)):
    meta = {"env": "point_nav", "proposal": "random", "obs_dim": 2, "act_dim": 2, "hidden": list(hidden),
            "init_std": 1.0, "inner_lr": 0.1, "num_inner_steps": 1, "first_order": False, "num_tasks": 2,
            "trajectories_per_task": 2, "horizon": 10, "num_skills": 4}
    return meta, {"policy": make_gaussian_policy(2, 2, hidden=hidden, init_std=1.0).state_dict(), "iteration": 1}


def _vime(hidden=(16,)):
    meta = {"env": "point_nav", "obs_dim": 2, "act_dim": 2, "policy_hidden": list(hidden), "policy_init_std": 1.0,
            "dynamics_hidden": [8], "prior_std": 0.5, "likelihood_std": 0.5}
    return meta, {"policy": make_gaussian_policy(2, 2, hidden=hidden, init_std=1.0).state_dict(),
                  "dynamics": BayesianDynamics(2, 2, hidden=(8,)).state_dict(),
                  "median_history": torch.full((3,), math.nan)}  # NaN-initialised by design: not a weight


def _seeds(hidden=(16,)):
    meta, _ = _diayn(hidden)
    return {**meta, "seeds": [0, 1]}, {"loss": {"actor_network_params.0.weight": torch.zeros(2, 6, 16)}}


KINDS = {  # format, state maker, loaders, (the width key, the float setting)
    "DIAYN": (DIAYN_FORMAT, _diayn, ["load_diayn_checkpoint", "load_discriminator", "load_skill_policy"],
              "hidden", "num_skills"),
    "MAML": (MAML_FORMAT, _maml, ["load_maml_checkpoint", "load_maml_policy"], "hidden", "inner_lr"),
    "VIME": (VIME_FORMAT, _vime, ["load_vime_checkpoint", "load_vime_dynamics", "load_vime_policy"],
             "policy_hidden", "prior_std"),
    "multi-seed DIAYN": (DIAYN_SEEDS_FORMAT, _seeds, [], "hidden", "num_skills"),
}


def _first_weights(entries):
    return next(value for value in entries.values() if isinstance(value, dict)
                and any(torch.is_tensor(t) and t.is_floating_point() for t in value.values()))


def _nan_weight(meta, entries, width_key, setting):
    weights = _first_weights(entries)
    name = next(k for k, t in weights.items() if t.is_floating_point())
    weights[name] = weights[name].clone().index_fill_(-1, torch.tensor([0]), math.nan)
    return meta, entries, rf"\w+\.{name.replace('.', '[.]')} = a .* tensor with \d+ non-finite values"


def _inf_weight(meta, entries, width_key, setting):
    weights = _first_weights(entries)
    name = next(k for k, t in weights.items() if t.is_floating_point())
    weights[name] = torch.full_like(weights[name], math.inf)
    return meta, entries, r"\S+ = a .* tensor with \d+ non-finite values"


def _nan_setting(meta, entries, width_key, setting):
    return {**meta, setting: math.nan}, entries, rf"meta\.{setting} = nan; expected finite values"


DAMAGES = {"a NaN weight": _nan_weight, "infinite weights": _inf_weight, "a NaN setting": _nan_setting}


def _save(fmt, directory, step, meta, entries):
    return fmt.save(Checkpointer(directory / "checkpoints", keep_all=True), step, meta, **entries)


@pytest.mark.parametrize("damage", list(DAMAGES))
@pytest.mark.parametrize("kind", list(KINDS))
def test_non_finite_content_is_refused_by_name_and_resume_falls_back(tmp_path, kind, damage):
    fmt, make, loaders, width_key, setting = KINDS[kind]
    meta, entries = make()
    good = _save(fmt, tmp_path, 1, meta, entries)
    bad_meta, bad_entries, why = DAMAGES[damage](*make(), width_key, setting)
    bad = _save(fmt, tmp_path, 2, bad_meta, bad_entries)
    for loader in loaders:
        with pytest.raises(CheckpointError, match=rf"cannot read checkpoint {bad} \(a {fmt.what} checkpoint\): {why}"):
            getattr(checkpoints, loader)(tmp_path)
    with pytest.warns(UserWarning, match=rf"skipping unreadable checkpoint {bad}"):
        _, state = fmt.load_for_resume(Checkpointer(tmp_path / "checkpoints"), meta)
    assert state["meta"] == meta and Checkpointer(tmp_path / "checkpoints").all() == [good]
    assert (tmp_path / "checkpoints" / "step_2.safetensors.unreadable").is_file()


def test_nan_in_data_that_is_not_a_weight_still_loads(tmp_path):
    """VIME's bonus normaliser starts as NaN: only weights and settings must be finite."""
    meta, entries = _vime()
    _save(VIME_FORMAT, tmp_path, 1, meta, entries)
    assert torch.isnan(checkpoints.load_vime_checkpoint(tmp_path)["median_history"]).all()


NETWORK_KINDS = [kind for kind in KINDS if KINDS[kind][0].networks]


FACTORIES = [(umrl.checkpoints.diayn, "make_skill_actor"), (umrl.checkpoints.diayn, "make_discriminator"),
             (umrl.checkpoints.maml, "make_gaussian_policy"), (umrl.checkpoints.vime, "make_gaussian_policy"),
             (umrl.checkpoints.vime, "BayesianDynamics")]


@pytest.mark.parametrize("kind", NETWORK_KINDS)
def test_huge_layers_in_a_small_file_are_refused_before_any_network_is_built(tmp_path, kind, monkeypatch):
    """A 27 kB file whose meta asks for two 100,000-wide layers made a loader allocate 14.4 GB."""
    fmt, make, loaders, width_key, _ = KINDS[kind]
    meta, entries = make()
    path = _save(fmt, tmp_path, 1, {**meta, width_key: [100_000, 100_000]}, entries)
    built = []
    for module, name in FACTORIES:
        monkeypatch.setattr(module, name, lambda *args, **kwargs: built.append(args))
    for loader in loaders:
        with pytest.raises(CheckpointError, match=rf"{path} \(a {fmt.what} checkpoint\): \w+: its meta describes "
                                                  r"layers \[.*100000, 100000.*\] of at least \d+ weights, but the "
                                                  r"file holds \d+; refused before building it"):
            getattr(checkpoints, loader)(tmp_path)
    assert built == []


BAD_WIDTHS = {
    "a width of zero": [0],
    "a negative width": [-16],
    "a width beyond the bound": [MAX_WIDTH + 1],
    "a text width": ["16"],
    "a boolean width": [True],
    "a fractional width": [16.5],
    "a million layers": [1] * 1_000_000,
}


@pytest.mark.parametrize("label", list(BAD_WIDTHS))
def test_widths_that_are_not_layer_sizes_are_refused_by_name(tmp_path, label):
    meta, entries = _maml()
    path = _save(MAML_FORMAT, tmp_path, 1, {**meta, "hidden": BAD_WIDTHS[label]}, entries)
    with pytest.raises(CheckpointError, match=rf"{path} \(a MAML checkpoint\): policy: layer widths .*; expected 2 "
                                              rf"to {MAX_LAYERS} whole numbers in \[1, {MAX_WIDTH}\]"):
        checkpoints.load_maml_policy(path)


@pytest.mark.parametrize("kind", NETWORK_KINDS)
def test_weights_of_other_shapes_than_the_meta_describes_are_refused(tmp_path, kind):
    """Enough weights for the meta's layers, of other shapes: the state dict does not load, and the file is named."""
    fmt, make, loaders, width_key, _ = KINDS[kind]
    meta, entries = make(hidden=(32,))
    path = _save(fmt, tmp_path, 1, {**meta, width_key: [16]}, entries)
    for loader in loaders:
        with pytest.raises(CheckpointError, match=rf"{path} \(a {fmt.what} checkpoint\): \w+ does not load into the "
                                                  r"network its meta describes \(RuntimeError: .*size mismatch"):
            getattr(checkpoints, loader)(tmp_path)


@pytest.mark.parametrize("meta", [None, [1, 2], "meta"])
def test_a_meta_that_is_not_a_dict_is_refused(tmp_path, meta):
    path = MAML_FORMAT.save(Checkpointer(tmp_path), 1, dict.fromkeys(MAML_FORMAT.meta_keys))
    state = read_checkpoint(path)
    with pytest.raises(CheckpointError, match=r"\(a MAML checkpoint\): meta is a \w+; expected a dict"):
        MAML_FORMAT.check({**state, "meta": meta}, path)


def test_checking_a_file_does_not_move_the_random_stream(tmp_path):
    meta, entries = _maml()
    path = _save(MAML_FORMAT, tmp_path, 1, meta, entries)
    torch.manual_seed(0)
    expected = torch.rand(3)
    torch.manual_seed(0)
    checkpoints.load_maml_checkpoint(path)
    assert torch.equal(torch.rand(3), expected)


def test_a_maml_resume_continues_from_the_checkpoint_before_a_tampered_one(tiny_maml_run):
    """A hash-valid NaN ``inner_lr`` written as the newest file: the recipe resumes from the previous one."""
    from umrl.trainers import compose
    from umrl.trainers.maml import train

    checkpointer = Checkpointer(tiny_maml_run / "checkpoints")
    good = checkpointer.latest()
    state = read_checkpoint(good)
    state["meta"]["inner_lr"] = math.nan
    tampered = MAML_FORMAT.save(Checkpointer(tiny_maml_run / "checkpoints", keep_all=True),
                               7, state["meta"], state["config"],
                               **{k: v for k, v in state.items() if k not in ("format", "meta", "config")})
    with pytest.warns(UserWarning, match=rf"skipping unreadable checkpoint {tampered}.*meta\.inner_lr = nan"):
        train(compose("maml", [*_tiny_maml_overrides(tiny_maml_run), "iterations=2", "resume=true"]))
    assert [p.name for p in checkpointer.all()] == [f"step_{i}.safetensors" for i in range(3)]  # MAML keeps all
    assert read_checkpoint(checkpointer.latest())["iteration"] == 2
    assert (tiny_maml_run / "checkpoints" / "step_7.safetensors.unreadable").is_file()


def _tiny_maml_overrides(directory):
    return ["proposal=oracle", "meta_batch_size=2", "trajectories_per_task=2", "env.horizon=10", "policy.hidden=[16]",
            "logger.backend=none", "progress=false", f"output_dir={directory}"]


@pytest.mark.parametrize("name", ["x" * 300, "step_1.pt\x00.txt"], ids=["a 300-byte name", "a NUL byte"])
def test_a_name_no_file_can_have_is_the_checkpoint_error(tmp_path, name):
    with pytest.raises(CheckpointError, match=r"cannot read checkpoint .* \(not opened\): "):
        checkpoints.load_maml_policy(str(tmp_path / name))


def test_a_write_past_the_file_size_limit_leaves_no_partial_file_and_says_so(tmp_path):
    """A full disk or a file-size limit: an ``OSError`` naming the file, and the half-written file removed."""
    path = tmp_path / "step_1.pt.tmp"
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, limit[1]))  # Python ignores SIGXFSZ: the write fails
    try:
        with pytest.raises(OSError, match=rf"cannot write checkpoint {path}: .*File too large.*previous checkpoint is "
                                          "intact"):
            write_checkpoint({"w": torch.zeros(100_000)}, path)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, limit)
    assert not path.exists()


def test_export_refuses_a_destination_no_folder_can_have_before_reading_the_source(tmp_path):
    from umrl.validation import InvalidValue

    with pytest.raises(InvalidValue, match=r"destination: got .*; expected a path whose every folder name has at most "
                                           r"255 bytes"):
        checkpoints.export_diayn_skills(tmp_path / "no_such_run", tmp_path / ("y" * 300))
