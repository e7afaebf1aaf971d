"""umrl.checkpoints: one format/version check for every loader and resume; saves carry the meta their loaders read."""
import pytest

from umrl import checkpoints
from umrl.checkpoints import DIAYN_FORMAT, MAML_FORMAT, VIME_FORMAT, CheckpointFormat
from umrl.checkpoints.file import write_checkpoint
from umrl.checkpoints.folder import Checkpointer
from umrl.configs import check_resume

LOADERS = {
    DIAYN_FORMAT: ["load_diayn_checkpoint", "load_discriminator", "load_skill_policy"],
    MAML_FORMAT: ["load_maml_checkpoint", "load_maml_policy"],
    VIME_FORMAT: ["load_vime_checkpoint", "load_vime_dynamics", "load_vime_policy"],
}


@pytest.mark.parametrize("fmt", list(LOADERS), ids=lambda f: f.what)
def test_every_loader_rejects_another_format(tmp_path, fmt):
    other = next(f for f in LOADERS if f is not fmt)
    other.save(Checkpointer(tmp_path / "checkpoints"), 3, dict.fromkeys(other.meta_keys))
    for name in LOADERS[fmt]:
        with pytest.raises(ValueError, match=f"not a {fmt.what} checkpoint.*{other.name}"):
            getattr(checkpoints, name)(tmp_path)
    write_checkpoint([1, 2], tmp_path / "step_9.pt")
    with pytest.raises(ValueError, match="format 'list'"):
        fmt.load(tmp_path / "step_9.pt")


def test_save_requires_the_meta_its_loaders_read(tmp_path):
    fmt = CheckpointFormat("test.v1", "Test", meta_keys=("env", "obs_dim"))
    with pytest.raises(ValueError, match=r"lacks \['obs_dim'\]"):
        fmt.save(Checkpointer(tmp_path), 1, {"env": "point_nav"})
    path = fmt.save(Checkpointer(tmp_path), 1, {"env": "point_nav", "obs_dim": 2}, {"seed": 0}, weights=[1.0])
    state = fmt.load(path)
    assert state == {"format": "test.v1", "meta": {"env": "point_nav", "obs_dim": 2}, "weights": [1.0],
                     "config": {"seed": 0}}


def test_resume_checks_format_and_meta(tmp_path):
    checkpointer = Checkpointer(tmp_path)
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        MAML_FORMAT.load_for_resume(checkpointer, {})
    meta = dict.fromkeys(MAML_FORMAT.meta_keys, 1)
    config = {"seed": 0, "iterations": 5}
    MAML_FORMAT.save(checkpointer, 1, meta, config)
    same = lambda saved: check_resume(saved, {**config, "iterations": 9})
    path, state = MAML_FORMAT.load_for_resume(checkpointer, meta, same)
    assert state["meta"] == meta and path == checkpointer.all()[-1]
    with pytest.raises(ValueError, match=rf"differs from {path}'s.*'horizon': \(1, 2\)"):
        MAML_FORMAT.load_for_resume(checkpointer, {**meta, "horizon": 2})
    with pytest.raises(ValueError, match="seed: checkpoint has 0, this run has 3"):
        MAML_FORMAT.load_for_resume(checkpointer, meta, lambda saved: check_resume(saved, {**config, "seed": 3}))
    with pytest.raises(ValueError, match="not a VIME checkpoint"):
        VIME_FORMAT.load_for_resume(checkpointer, {})


@pytest.mark.parametrize("fmt", list(LOADERS), ids=lambda f: f.what)
def test_a_checkpoint_of_another_observation_size_is_refused_by_every_loader(tmp_path, fmt):
    """A run of the 107-D ant (x-y in the observation) does not load for today's 105-D ant: one clear error."""
    meta = {**dict.fromkeys(fmt.meta_keys), "env": "ant", "obs_dim": 107}
    fmt.save(Checkpointer(tmp_path / "old" / "checkpoints"), 3, meta)
    for name in LOADERS[fmt]:
        with pytest.raises(ValueError, match=r"observation size: got 107 \(.*checkpoint .*step_3\.safetensors\); expected "
                                             r"105, the observation size of env 'ant'"):
            getattr(checkpoints, name)(tmp_path / "old")
    fmt.save(Checkpointer(tmp_path / "new" / "checkpoints"), 3, {**meta, "obs_dim": 105})
    assert fmt.load(tmp_path / "new")["meta"]["obs_dim"] == 105


def test_meta_test_refuses_an_old_ant_checkpoint_before_any_work(tmp_path):
    from umrl.metatest import load_initialisation

    MAML_FORMAT.save(Checkpointer(tmp_path / "checkpoints"), 1,
                     {**dict.fromkeys(MAML_FORMAT.meta_keys), "env": "ant", "obs_dim": 107})
    with pytest.raises(ValueError, match=r"observation size: got 107 .*expected 105"):
        load_initialisation("oracle", "ant", tmp_path, seed=0)


def test_public_names():
    expected = {"load_diayn_checkpoint", "load_discriminator", "load_skill_policy", "load_maml_checkpoint",
                "load_maml_policy", "load_vime_checkpoint", "load_vime_dynamics", "load_vime_policy",
                "save_diayn_checkpoint", "save_maml_checkpoint", "save_vime_checkpoint"}
    assert expected <= set(checkpoints.__all__)
    assert all(callable(getattr(checkpoints, name)) for name in expected)
