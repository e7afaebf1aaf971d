"""Smoke runs of the timing benchmarks on tiny settings: they build what the recipes build and print their table."""
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]


def test_meta_iteration_times_the_recipes_step_for_each_variant():
    out = subprocess.run(
        [sys.executable, str(REPO / "benchmarks" / "meta_iteration.py"), "--preset", "reference", "--tasks", "2",
         "--trajectories", "2", "--repeats", "1", "--task-loop", "batched", "loop", "--hvp", "gauss_newton", "analytic"],
        capture_output=True, text=True, timeout=300, check=True, cwd=REPO,
    ).stdout
    assert "reference: point_nav 2 tasks x 2 traj x 100 steps" in out
    table = [line.split() for line in out.splitlines() if "learn/floor" in line]
    assert [row[0] for row in table] == ["batched/gauss_newton", "batched/analytic", "loop/gauss_newton"]
    for row in table:
        learn, floor = float(row[row.index("learn") + 1]), float(row[row.index("floor") + 1])
        ratio = float(row[row.index("learn/floor") + 1])
        # no timing claim (a loaded machine measures a low matmul rate), but the ratio is that of the printed figures
        half = 0.005  # each figure is printed to two decimals
        assert learn > 0 and floor > half
        assert (learn - half) / (floor + half) - half <= ratio <= (learn + half) / (floor - half) + half
    parts = [line.split() for line in out.splitlines() if "learn = inner" in line]
    assert len(parts) == 3
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
    command = [sys.executable, str(REPO / "scripts" / "diagnostics" / "skill_coverage.py"), str(directory), "--horizons", "5",
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


def test_episode_lengths_replays_a_cell_with_its_own_episodes(tmp_path):
    """The replay goes through meta_test with the cell's settings: its returns are the cell's, to the last digit."""
    from umrl.metatest import AdaptationConfig, CellSpec, run_cell

    cell = run_cell(CellSpec(method="scratch", env="point_nav", seed=3, output=str(tmp_path / "cell.csv"), num_tasks=3,
                             protocol=AdaptationConfig(num_steps=2, num_trajectories=4)))
    maml = tmp_path / "maml"
    subprocess.run([sys.executable, str(REPO / "recipes" / "maml.py"), "iterations=1", "meta_batch_size=2",
                    "trajectories_per_task=2", "env.horizon=5", "logger.backend=none", "progress=false",
                    f"output_dir={maml}"], capture_output=True, text=True, timeout=300, check=True, cwd=REPO)
    out = subprocess.run([sys.executable, str(REPO / "scripts" / "diagnostics" / "episode_lengths.py"),
                          str(Path(cell).with_suffix(".json")), "--stand-still", "--maml-checkpoints",
                          str(maml / "checkpoints" / "step_1.safetensors")],
                         capture_output=True, text=True, timeout=300, check=True, cwd=REPO).stdout
    rows = [line.split() for line in out.splitlines()[1:]]
    replayed = [r for r in rows if r[0] == "point_nav/scratch/seed3"]
    assert [int(r[1]) for r in replayed] == [0, 1, 2]
    for _, _, ret, length, terminated, per_step, end_error, match in replayed:
        assert float(match) == 0.0  # the cell's recorded mean return, exactly
        assert 1 <= float(length) <= 100 and 0 <= float(terminated) <= 1
        assert abs(float(ret) - float(length) * float(per_step)) < 0.05 * float(length) + 0.05
        assert 0 <= float(end_error) < 100 * 0.1 * 2**0.5 + 0.5  # the goal is within 0.5 and a step moves <= 0.1
    (still,) = [r for r in rows if r[0] == "point_nav/stand_still/seed3"]
    # zero actions never leave the origin: every step costs the goal's distance, for all 100 steps
    from umrl.envs import get_task_family

    expected = -100 * get_task_family("point_nav").eval_tasks(3).norm(dim=-1).mean().item()
    assert abs(float(still[2]) - expected) < 0.05 and still[3:5] == ["100.0", "0.00"]
    assert abs(float(still[6]) - expected / -100) < 1e-3  # it ends where it started: the goal's distance away
    (zero_shot,) = [r for r in rows if r[0].endswith("/step_1")]  # the MAML policy, unadapted, on the same tasks
    assert zero_shot[1] == "0" and 1 <= float(zero_shot[3]) <= 100


def _ended_batch(**next_keys):
    """[T=1, N=2, H=3]: copy 0 terminates at step 1, copy 1 at step 2; reward 1 per step; tasks (1, 0)."""
    from tensordict import TensorDict

    terminated = torch.tensor([[[False], [True], [False]], [[False], [False], [True]]])[None]
    keys = {"reward": torch.ones(1, 2, 3, 1), "done": terminated, "terminated": terminated,
            "observation": torch.zeros(1, 2, 3, 105), **next_keys}
    return TensorDict({"task": torch.tensor([1.0, 0.0]).expand(1, 2, 3, 2), "next": keys}, [1, 2, 3])


def test_episode_stats_counts_first_episodes_and_ant_jumps():
    from script_loading import load_script

    bench = load_script("scripts/diagnostics/episode_lengths.py")
    observation = torch.zeros(1, 2, 3, 105)
    observation[0, 0, 1, 0] = 1.2  # copy 0 ends at step 1 with its torso above 1.0 (a jump), copy 1 at step 2 (below)
    xy = torch.zeros(1, 2, 3, 2)
    xy[0, 0, 1] = torch.tensor([1.0, 3.0])  # copy 0 ends 3 from its goal (1, 0), copy 1 ends 5 from it
    xy[0, 1, 2] = torch.tensor([4.0, 4.0])
    batch = _ended_batch(observation=observation, xy_position=xy)
    stats = bench.episode_stats(batch, "ant")
    assert stats == {"return": 2.5, "length": 2.5, "terminated": 1.0, "reward/step": 1.0, "jumped": 0.5,
                     "end error": 4.0}


def test_episode_stats_end_error_of_a_velocity_task_uses_the_mean_velocity():
    from script_loading import load_script

    bench = load_script("scripts/diagnostics/episode_lengths.py")
    velocity = torch.tensor([[[1.0], [3.0], [9.0]], [[0.0], [1.0], [2.0]]])[None]  # copy 0's step 2 is past its end
    batch = _ended_batch(x_velocity=velocity)
    batch["task"] = torch.full((1, 2, 3, 1), 1.5)
    stats = bench.episode_stats(batch, "half_cheetah")
    assert stats["jumped"] != stats["jumped"]  # NaN: not the Ant CMP
    assert stats["end error"] == pytest.approx((abs(2.0 - 1.5) + abs(1.0 - 1.5)) / 2)


def test_throughput_scaling_prints_the_table_after_every_repeat(capsys):
    """A scaling run stopped by a time limit still reports: the table of the repeats done so far follows each one."""
    from argparse import Namespace

    from script_loading import load_script

    throughput = load_script("benchmarks/throughput.py")
    args = Namespace(scaling_batch=4, threads_list=[1], mujoco_steps=8, quick=False)
    with torch.no_grad():
        final = throughput.scaling_table(args, repeats=2)
    printed = capsys.readouterr().out
    assert "medians of 1 interleaved repeats, 1 to go" in printed and "medians of 2" not in printed
    assert final.splitlines()[0].endswith("(medians of 2 interleaved repeats)")
    for table in (printed, final):
        rows = [line.split() for line in table.splitlines() if line.startswith(("half_cheetah", "ant"))]
        assert [(row[0], row[1]) for row in rows] == [("half_cheetah", "1"), ("ant", "1")]
        assert "2 shards/limit" in table and all(len(row) == 11 for row in rows)
        assert all(float(x.replace(",", "")) > 0 for row in rows for x in row[2:])
        for row in rows:  # the policy's cost bounds the ratio: serial <= overlapped <= 1 (here on 1 thread: equal)
            serial, overlap = float(row[-2]), float(row[-1])
            assert serial <= overlap <= 1 and serial == overlap


def test_action_noise_adapts_like_the_suite_and_replaces_only_the_log_std(tiny_maml_run, capsys):
    """Its ``saved`` arm is the suite's MAML cell (same returns as meta_test of load_initialisation); a replaced
    log-std changes the sampled noise and nothing else; the table has one row per run and log-std."""
    import numpy as np
    from script_loading import load_script
    from tensordict import TensorDict

    from umrl.checkpoints import load_maml_policy
    from umrl.envs.tasks import get_task_family
    from umrl.metatest import AdaptationConfig, load_initialisation, meta_test
    from umrl.modules import policy_log_std

    bench = load_script("scripts/diagnostics/action_noise.py")
    config = AdaptationConfig(num_steps=2, num_trajectories=3, horizon=10, sgd_schedule="reference")
    tasks = get_task_family("point_nav").eval_tasks(2)
    saved, returns = bench.adapt(str(tiny_maml_run), None, env="point_nav", tasks=tasks, seed=1, config=config)
    init = load_initialisation("oracle", "point_nav", tiny_maml_run, seed=1)
    expected, _ = meta_test(init, "point_nav", tasks, lr=init.lr, seed=1, config=config, skill_trajectories=1)
    np.testing.assert_array_equal(returns, expected.numpy())
    assert saved == policy_log_std(load_maml_policy(tiny_maml_run)[0]).mean().item()

    policy = load_maml_policy(tiny_maml_run)[0]
    policy_log_std(policy).data.fill_(-3.0)
    out = policy(TensorDict({"observation": torch.zeros(4, 2)}, [4]))
    torch.testing.assert_close(out["scale"], torch.full((4, 2), float(np.exp(-3.0))))
    _, replaced = bench.adapt(str(tiny_maml_run), -3.0, env="point_nav", tasks=tasks, seed=1, config=config)
    assert not np.array_equal(replaced, returns)

    bench.main(["--run", f"tiny={tiny_maml_run}", "--log-std", "saved", "-3", "--seeds", "1", "--steps", "2",
                "--num-tasks", "2", "--trajectories", "3"])
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[:6] == ["run", "log-std", "saved", "k=0", "k=1", "k=2"]
    assert [line.split()[:2] for line in lines[1:]] == [["tiny", "saved"], ["tiny", "-3.00"]]


def test_kl_hessian_fraction_steps_from_one_batch_and_undoes_each_step(tmp_path, capsys):
    """Two steps at the same fraction from the same batch are identical (each step undone, the batch reused), the
    log-std's KL is the Gaussian KL, ``:init`` starts from the recipe's init (log σ = log init_std = 0), and a
    fraction outside (0, 1] is refused."""
    from script_loading import load_script

    from umrl.trainers import compose
    from umrl.trainers.maml import train

    train(compose("maml", ["proposal=oracle", "iterations=1", "meta_batch_size=3", "trajectories_per_task=4",
                           "env.horizon=10", "policy.hidden=[16]", "logger.backend=none", "progress=false",
                           f"output_dir={tmp_path}"]))
    bench = load_script("scripts/diagnostics/kl_hessian_fraction.py")
    rows = bench.compare_steps(str(tmp_path), from_init=False, seed=0, fractions=[1.0, 1.0, 0.5], draws=2,
                               threads=1, skills=None)
    assert [(r["fraction"], r["draw"]) for r in rows] == [(1.0, 0), (1.0, 0), (0.5, 0), (0.5, 1)]
    assert rows[0]["accepted"] == 1 and rows[0]["dlogstd"] != 0
    for key in ("dlogstd", "kl", "improvement", "mean_net_norm", "log_std"):
        assert rows[1][key] == rows[0][key]
    assert rows[1]["cosine"] == pytest.approx(1.0)
    assert rows[2]["log_std"] == rows[0]["log_std"] != 0.0
    assert rows[2]["dlogstd"] != rows[3]["dlogstd"]  # two subsamples, two Hessians

    delta = torch.tensor([0.3, -0.2])
    normal = torch.distributions.Normal
    expected = torch.distributions.kl_divergence(normal(0.0, torch.ones(2)), normal(0.0, delta.exp())).sum()
    assert bench.sigma_kl(delta) == pytest.approx(expected.item(), rel=1e-6)

    init = bench.compare_steps(str(tmp_path), from_init=True, seed=0, fractions=[1.0], draws=1, threads=1,
                               skills=None)
    assert init[0]["log_std"] == 0.0
    with pytest.raises(SystemExit):
        bench.main(["--run", f"tiny={tmp_path}", "--fractions", "1.5"])
    assert "--fractions: got [1.5]; expected values in (0, 1]" in capsys.readouterr().err


def test_step_size_reproduces_the_suites_update_at_its_own_scale(tiny_maml_run, capsys):
    """At the reference schedule's own scale (1 at the first update, 0.5 later) the scaled update's returns are
    meta_test's at that step; scale 0 leaves the action means where they were; negative scales are refused."""
    import numpy as np
    from script_loading import load_script

    from umrl.envs.tasks import get_task_family
    from umrl.metatest import AdaptationConfig, load_initialisation, meta_test

    bench = load_script("scripts/diagnostics/step_size.py")
    config = AdaptationConfig(num_steps=2, num_trajectories=3, horizon=10, sgd_schedule="reference")
    tasks = get_task_family("point_nav").eval_tasks(2)
    init = load_initialisation("oracle", "point_nav", tiny_maml_run, seed=1)
    expected, _ = meta_test(init, "point_nav", tasks, lr=init.lr, seed=1, config=config, skill_trajectories=1)
    for step, own_scale in ((1, 1.0), (2, 0.5)):
        out = bench.scaled_step(str(tiny_maml_run), step=step, scales=[0.0, own_scale, 3.0], env_name="point_nav",
                                tasks=tasks, seed=1, config=config)
        np.testing.assert_array_equal(out["returns"][1], expected[step].numpy())
        assert out["rms_shift"][0] == 0.0 < out["rms_shift"][1] < out["rms_shift"][2]

    bench.main(["--run", f"tiny={tiny_maml_run}", "--step", "2", "--scales", "0", "0.5", "--seeds", "1",
                "--num-tasks", "2", "--trajectories", "3"])
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].split() == ["run", "seed", "c=0", "c=0.5"]
    assert [line.split()[:2] for line in lines[2:]] == [["tiny", "1"], ["tiny", "all"]]
    with pytest.raises(SystemExit):
        bench.main(["--run", f"tiny={tiny_maml_run}", "--scales", "-1"])
    assert "--scales: got [-1.0]; expected values >= 0" in capsys.readouterr().err


def test_step_size_decomposition_rebuilds_both_updates_from_their_pushes(tiny_maml_run, capsys):
    """θ0·B0 and θ1·B1 are the first and second updates' own action-mean shifts at scale 1 (as scaled_step
    measures them); the uniform push alone is linear in the push: half the push moves the means half as far."""
    import numpy as np
    from script_loading import load_script

    from umrl.envs.tasks import get_task_family
    from umrl.metatest import AdaptationConfig

    bench = load_script("scripts/diagnostics/step_size.py")
    config = AdaptationConfig(num_steps=2, num_trajectories=3, horizon=10, sgd_schedule="reference")
    tasks = get_task_family("point_nav").eval_tasks(2)
    out = bench.decompose(str(tiny_maml_run), env_name="point_nav", tasks=tasks, seed=1, config=config)
    for step, key in ((1, "θ0·B0"), (2, "θ1·B1")):
        own = bench.scaled_step(str(tiny_maml_run), step=step, scales=[1.0], env_name="point_nav", tasks=tasks,
                                seed=1, config=config)["rms_shift"][0]
        assert out[key] == pytest.approx(own, rel=1e-5)
    assert all(np.isfinite(v) and v >= 0 for v in out.values())
    assert out["θ0·B1"] != out["θ1·B1"] and out["θ1·B0"] != out["θ0·B0"]

    adapter, lr = bench.make_adapter(str(tiny_maml_run), env_name="point_nav", tasks=tasks, seed=1, config=config)
    batch = adapter.collect()
    before = adapter.params.detach().clone()
    adapter.step(batch)  # writes the batch's advantages

    # "last layer B0": the uniform push of the first batch moving only the last linear layer, done by hand
    push = bench.mean_push(adapter, before, batch)
    valid = batch["mask"].unsqueeze(-1).to(push.dtype)
    total = (push * valid).sum((1, 2))
    _, weight_key, bias_key = adapter.functional.batched.layers[-1]
    moved = before.clone()
    leaves = [moved.get(weight_key).requires_grad_(), moved.get(bias_key).requires_grad_()]
    loc = adapter.functional.dist_params(moved, batch)["loc"]
    uniform = total[:, None, None] / valid.sum((1, 2), keepdim=True) * valid
    gradients = torch.autograd.grad((loc * uniform).sum(), leaves)
    with torch.no_grad():
        for leaf, gradient in zip(leaves, gradients, strict=True):
            leaf.sub_(lr * gradient)
        shift = (adapter.functional.dist_params(moved, batch)["loc"] - loc)[batch["mask"]]
    response = shift.square().sum(-1).mean().sqrt() / (lr * total.norm(dim=-1).square().mean().sqrt())
    assert out["last layer B0"] == pytest.approx(response.item(), rel=1e-4)

    push = bench.mean_push(adapter, adapter.params, batch)
    small = 1e-2 * push  # small enough for the step to be linear in the push, large against float rounding
    assert bench.mean_shift(adapter, adapter.params, batch, small / 2, lr) == pytest.approx(
        bench.mean_shift(adapter, adapter.params, batch, small, lr) / 2, rel=1e-2)
    adapter.env.close()

    bench.main(["--run", f"tiny={tiny_maml_run}", "--decompose", "--seeds", "1", "--num-tasks", "2",
                "--trajectories", "3"])
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].split()[:4] == ["run", "seed", "θ0·B0", "θ1·B1"]
    assert [line.split()[:2] for line in lines[2:]] == [["tiny", "1"], ["tiny", "mean"]]


def test_action_noise_refuses_a_later_factor_the_protocol_refuses(capsys):
    from script_loading import load_script

    with pytest.raises(SystemExit):
        load_script("scripts/diagnostics/action_noise.py").main(["--run", "x=y", "--schedule", "swept", "--later-factor", "0"])
    assert "protocol.sgd_later_factor: got 0.0; expected a finite number > 0" in capsys.readouterr().err


@pytest.mark.parametrize("script", ["scripts/diagnostics/action_noise.py", "scripts/diagnostics/kl_hessian_fraction.py",
                                    "scripts/diagnostics/step_size.py"])
@pytest.mark.parametrize("spec", ["no-label", "=path", "label="])
def test_run_options_refuse_a_value_without_label_and_path(script, spec, capsys):
    from script_loading import load_script

    with pytest.raises(SystemExit):
        load_script(script).main(["--run", spec])
    assert f"--run: got {spec!r}; expected LABEL=PATH" in capsys.readouterr().err


@pytest.mark.parametrize("expect, returncode, output, kind", [
    ("refuse", 1, "Traceback\nValueError: seed: got 1e99; expected an integer", "clear"),
    ("refuse", 1, "Traceback\nIndexError: tuple index out of range", "obscure"),
    ("refuse", None, "", "obscure"),  # past the time limit
    ("refuse", 0, "done", "silent"),
    ("warn", 0, "UserWarning: collector.total_frames: got 100 (...); expected a multiple", "clear"),
    ("warn", 0, "done", "silent"),
    ("run", 0, "done", "fine"),
    ("run", 1, "IndexError: tuple index out of range", "obscure"),
])
def test_bad_input_probe_sorts_outcomes(expect, returncode, output, kind):
    from script_loading import load_script

    assert load_script("scripts/diagnostics/bad_inputs.py").verdict(expect, returncode, output)[0] == kind


def test_bad_input_probe_runs_a_case_in_a_fresh_process(tmp_path):
    from script_loading import load_script

    probe = load_script("scripts/diagnostics/bad_inputs.py")
    case = next(case for case in probe.CASES if case.label == "make_task_env with a list")
    kind, line = probe.verdict(case.expect, *probe.run(case.argv, str(tmp_path), 120)[:2])
    assert kind == "clear" and "tasks: got [0.1, 0.2]" in line


def test_initial_policy_diagnostic_measures_clipping_and_distance():
    """scratch's fresh Gaussian (loc ≈ 0, σ = 1) puts P(|N(0, 1)| > 1) ≈ 0.32 of its action entries outside the
    bounds; the line names every measured quantity."""
    from script_loading import load_script

    bench = load_script("scripts/diagnostics/initial_policy.py")
    line = bench.describe("scratch", None, "point_nav", seed=0, trajectories=4, position_key="position")
    fields = dict(part.rsplit(" ", 1) for part in line.split(": ", 1)[1].split(", "))
    assert 0.25 < float(fields["actions outside the bounds"]) < 0.40
    assert float(fields["log-std"]) == 0.0 and float(fields["mean |loc|"]) < 0.2
    assert 0 < float(fields["end distance from the start"]) < 3 and float(fields["return k=0"]) < 0
