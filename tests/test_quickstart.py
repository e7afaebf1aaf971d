"""examples/quickstart.py runs end to end (DIAYN -> UML-DIAYN MAML -> meta-test beside scratch), here at a smaller
size, on one torch thread whatever the caller's count, which it leaves as it was."""
import math

import torch
from script_loading import load_script


def test_quickstart_trains_meta_trains_and_meta_tests_beside_scratch(tmp_path):
    quickstart = load_script("examples/quickstart.py").quickstart
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        returns = quickstart(str(tmp_path), steps=1,
                             diayn=["collector.total_frames=1600", "eval.every=1600", "checkpoint.every=1600",
                                    "logger.backend=none"],
                             maml=["iterations=1", "trajectories_per_task=2", "logger.backend=none"])
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)
    assert sorted(returns) == ["scratch", "uml_diayn"]
    assert all(len(curve) == 2 and all(map(math.isfinite, curve)) for curve in returns.values())  # k = 0 and 1
    assert (tmp_path / "meta_test_uml_diayn.csv").is_file() and (tmp_path / "meta_test_scratch.csv").is_file()
    assert (tmp_path / "maml" / "checkpoints" / "step_1.safetensors").is_file()
