"""examples/quickstart.py runs end to end (DIAYN -> UML-DIAYN MAML -> meta-test), here at a smaller size."""
import math

from script_loading import load_script


def test_quickstart_trains_meta_trains_and_meta_tests(tmp_path):
    quickstart = load_script("examples/quickstart.py").quickstart
    returns = quickstart(str(tmp_path), steps=1,
                         diayn=["collector.total_frames=1600", "eval.every=1600", "checkpoint.every=1600",
                                "logger.backend=none"],
                         maml=["iterations=1", "trajectories_per_task=2", "logger.backend=none"])
    assert len(returns) == 2 and all(math.isfinite(r) for r in returns)  # k = 0 and k = 1
    assert (tmp_path / "meta_test.csv").is_file()
    assert (tmp_path / "maml" / "checkpoints" / "step_1.pt").is_file()
