"""Smoke runs of the timing benchmarks on tiny settings: they build what the recipes build and print their table."""
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_meta_iteration_times_the_recipes_step_for_each_variant():
    out = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "meta_iteration.py"), "--preset", "reference", "--tasks", "2",
         "--trajectories", "2", "--repeats", "1", "--task-loop", "batched", "loop"],
        capture_output=True, text=True, timeout=300, check=True, cwd=REPO,
    ).stdout
    assert "reference: point_nav 2 tasks x 2 traj x 100 steps" in out
    table = [line.split() for line in out.splitlines() if "learn/floor" in line]
    assert [row[0] for row in table] == ["batched", "loop"]
    for row in table:
        learn, floor = float(row[row.index("learn") + 1]), float(row[row.index("floor") + 1])
        ratio = float(row[row.index("learn/floor") + 1])
        # no timing claim (a loaded machine measures a low matmul rate), but the ratio is that of the printed figures
        half = 0.005  # each figure is printed to two decimals
        assert learn > 0 and floor > half
        assert (learn - half) / (floor + half) - half <= ratio <= (learn + half) / (floor - half) + half
    parts = [line.split() for line in out.splitlines() if "learn = inner" in line]
    assert len(parts) == 2
    for row, learn_row in zip(parts, table):
        seconds = [float(row[row.index(k) + 1]) for k in ("inner", "objective", "direction", "search")]
        assert all(t >= 0 for t in seconds) and seconds[2] > 0  # ten CG products take time
        learn = float(learn_row[learn_row.index("learn") + 1])
        # one iteration (--repeats 1): the parts add up, to the rounding of five figures printed to two decimals
        assert abs(sum(seconds) - learn) <= 5 * 0.005 + 1e-9


def test_meta_iteration_counts_both_parts_of_the_learning_step(tmp_path):
    """The recipe enters its learning context twice (inner adaptation, then the TRPO step, with the query collection
    between): the benchmark's FLOP count is the sum of a counter per part, not one counter that forgets the first."""
    from script_loading import load_script

    bench = load_script("benchmarks/meta_iteration.py")
    variant = bench.Variant([*bench.PRESETS["reference"], "meta_batch_size=2", "trajectories_per_task=2",
                             "env.horizon=10", "proposal=oracle", "logger.backend=none", f"output_dir={tmp_path}"])
    counters = []
    variant.iteration(counters)
    assert len(counters) == 2 and all(c.get_total_flops() > 0 for c in counters)
    assert counters[1].get_total_flops() > counters[0].get_total_flops()  # CG and line search outweigh one adaptation


def test_skill_coverage_evaluates_a_checkpoint_at_each_horizon_beside_a_random_policy(tiny_diayn_checkpoint, tmp_path):
    from umrl.envs import get_env_spec

    directory, _ = tiny_diayn_checkpoint
    command = [sys.executable, str(REPO / "benchmarks" / "skill_coverage.py"), str(directory), "--horizons", "5",
               "20", "--episodes", "2", "--out", str(tmp_path / "figures")]
    out = subprocess.run(command, capture_output=True, text=True, timeout=300, check=True, cwd=REPO).stdout
    assert subprocess.run(command, capture_output=True, text=True, timeout=300, check=True, cwd=REPO).stdout == out
    rows = {(r[1], r[2]): [float(x) for x in r[3:8]] for r in (line.split() for line in out.splitlines())
            if r and r[0] == "diayn_step_1"}
    assert set(rows) == {(h, p) for h in ("5", "20") for p in ("skills", "random")}
    for values in rows.values():
        accuracy, _, _, task_median, task_max = values
        assert 0 <= accuracy <= 1 and 0 <= task_median <= task_max
    assert rows["20", "skills"] != rows["20", "random"]  # the trained actor is the one rolled out
    tasks = get_env_spec("point_nav").eval_tasks()
    low, high = tasks.min(0).values.tolist(), tasks.max(0).values.tolist()
    assert f"[{low[0]:.2f}, {high[0]:.2f}] [{low[1]:.2f}, {high[1]:.2f}]" in out
    for horizon in (5, 20):
        assert (tmp_path / "figures" / f"diayn_step_1_h{horizon}.png").stat().st_size > 1000
