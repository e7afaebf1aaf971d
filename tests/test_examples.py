"""examples/: each runs end to end at its tiny default sizes."""
import torch
from script_loading import load_script


def test_meta_train_from_python_trains_checkpoints_and_meta_tests(tmp_path):
    example = load_script("examples/meta_train_from_python.py")
    curve = example.main(["--output", str(tmp_path / "maml"), "--iterations", "2", "--tasks", "2", "--steps", "1"])
    assert curve.shape == (2,) and torch.isfinite(curve).all()  # k = 0 and k = 1
    assert sorted(p.name for p in (tmp_path / "maml" / "checkpoints").glob("step_*")) == [
        "step_0.safetensors", "step_1.safetensors", "step_2.safetensors"]
