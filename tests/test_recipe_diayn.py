"""Smoke tests of recipes/diayn.py: a tiny run completes, checkpoints, resumes, draws the coverage figure."""
import subprocess
import sys

import pytest
import torch
from script_loading import REPO
from tensordict import TensorDict

from umrl.checkpoints import load_diayn_checkpoint, load_discriminator, load_skill_policy
from umrl.trainers import compose

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


def load_recipe():
    import umrl.trainers.diayn

    return umrl.trainers.diayn


def tiny_config(output_dir, *overrides):
    return compose("diayn", [
            "logger.backend=none", "progress=false", f"output_dir={output_dir}", "num_skills=3",
            "env.num_envs=4", "env.horizon=10", "collector.frames_per_batch=40", "collector.total_frames=120",
            "collector.init_random_frames=40", "optim.updates_per_frame=0.25", "network.hidden=[16,16]",
            "network.discriminator_hidden=[16]", "replay_buffer.batch_size=16", "eval.every=80",
            "eval.episodes_per_skill=2", "checkpoint.every=80", *overrides,
    ])


ENVS = ["point_nav", "half_cheetah"]


@pytest.mark.parametrize("env_name", ENVS)
def test_run_checkpoint_resume_figure(tmp_path, env_name):
    recipe = load_recipe()
    result = recipe.train(tiny_config(tmp_path, f"env.name={env_name}"))
    assert 0.0 <= result["eval/final_state_accuracy"] <= 1.0
    assert (tmp_path / "seed0" / "figures" / "skill_coverage.png").stat().st_size > 1000
    assert (tmp_path / "seed0" / "figures" / "skill_coverage_80.png").is_file()
    first = load_diayn_checkpoint(tmp_path)
    assert first["counters"]["frames"] == 120 and first["counters"]["updates"] > 0
    assert (tmp_path / "checkpoints" / "config.yaml").is_file() and (tmp_path / "seed0" / "checkpoints").is_dir()

    resumed = recipe.train(tiny_config(tmp_path, f"env.name={env_name}", "resume=true", "collector.total_frames=200"))
    second = load_diayn_checkpoint(tmp_path)
    assert second["counters"]["frames"] == 200
    assert second["counters"]["updates"] > first["counters"]["updates"]
    assert resumed["train/frames"] == 200

    discriminator, num_skills, obs_dim = load_discriminator(tmp_path)
    actor, num_skills_actor, obs_dim_actor = load_skill_policy(tmp_path / "checkpoints")
    assert (num_skills, num_skills_actor) == (3, 3) and obs_dim == obs_dim_actor == second["meta"]["obs_dim"]
    obs = torch.randn(5, obs_dim)
    td = TensorDict({"observation": obs, "skill": torch.eye(3)[[0, 1, 2, 0, 1]]}, [5])
    assert actor(td)["action"].shape == (5, second["meta"]["act_dim"])
    weight = second["discriminator"]["module.0.weight"]
    torch.testing.assert_close(discriminator.module[0].weight, weight)
    assert not any(p.requires_grad for p in discriminator.parameters())


def test_discriminator_on_chosen_observation_dims(tmp_path):
    """network.discriminator_input_dims (DIAYN's "prior" ablation): the trained and the reloaded D read only them."""
    recipe = load_recipe()
    recipe.train(tiny_config(tmp_path, "env.name=half_cheetah", "network.discriminator_input_dims=[8]"))
    state = load_diayn_checkpoint(tmp_path)
    assert state["meta"]["discriminator_input_dims"] == [8]
    discriminator, _, obs_dim = load_discriminator(tmp_path)
    obs = torch.randn(6, obs_dim)
    others = obs.clone()
    others[:, [d for d in range(obs_dim) if d != 8]] = torch.randn(6, obs_dim - 1)
    logits = discriminator(TensorDict({"observation": obs}, [6]))["skill_logits"]
    torch.testing.assert_close(discriminator(TensorDict({"observation": others}, [6]))["skill_logits"], logits)
    torch.testing.assert_close(discriminator.module[1][0].weight, state["discriminator"]["module.1.0.weight"])


def test_resume_without_checkpoint_fails_clearly(tmp_path):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        load_recipe().train(tiny_config(tmp_path, "resume=true"))


def test_exported_skills_load_like_the_run_and_refuse_resume(tmp_path):
    """python -m umrl.checkpoints.export_skills: the copy holds the run's actor and discriminator (equal tensors) and
    its config, without replay buffer or optimisers (those stay in the program's checkpoint); the loaders read it, a
    resume from it is refused by name."""
    run, skills = tmp_path / "run", tmp_path / "skills"
    load_recipe().train(tiny_config(run))
    proc = subprocess.run([sys.executable, "-m", "umrl.checkpoints.export_skills", str(run), str(skills)],
                          check=True, capture_output=True, text=True, timeout=120, cwd=REPO)
    written = skills / "checkpoints" / "step_120.safetensors"
    assert proc.stdout.strip() == str(written)
    source, copy = load_diayn_checkpoint(run), load_diayn_checkpoint(skills)
    assert set(copy) == set(source) == {"format", "meta", "config", "actor", "discriminator", "counters"}
    assert written.stat().st_size < (run / "checkpoints" / "step_120.safetensors").stat().st_size / 2
    assert (copy["meta"], copy["config"], copy["counters"]) == (source["meta"], source["config"], source["counters"])
    assert ((skills / "checkpoints" / "config.yaml").read_text()
            == (run / "seed0" / "checkpoints" / "config.yaml").read_text())
    for load in (load_discriminator, load_skill_policy):
        for a, b in zip(load(run)[0].parameters(), load(skills)[0].parameters(), strict=True):
            torch.testing.assert_close(a, b, rtol=0, atol=0)
    with pytest.raises(ValueError, match="step_120.safetensors is not a multi-seed DIAYN checkpoint .*'umrl.diayn.v1'"):
        load_recipe().train(tiny_config(skills, "resume=true", "collector.total_frames=200"))


def test_a_run_of_several_seeds_writes_each_seeds_skills(tmp_path):
    """seeds=[0,2]: one program, a folder per seed that every loader reads; the run folder itself names them."""
    result = load_recipe().train(tiny_config(tmp_path, "seeds=[0,2]"))
    assert result["runs"] == [str(tmp_path / "seed0"), str(tmp_path / "seed2")]
    assert {"seed0/eval/final_state_accuracy", "seed2/train/loss_qvalue"} <= set(result)
    for seed in (0, 2):
        state = load_diayn_checkpoint(tmp_path / f"seed{seed}")
        assert state["config"]["seed"] == seed and state["counters"]["frames"] == 120
        assert (tmp_path / f"seed{seed}" / "figures" / "skill_coverage.png").is_file()
    with pytest.raises(ValueError, match="is a DIAYN run of 2 seeds: point to one seed's folder"):
        load_discriminator(tmp_path)


def test_cli_rejects_one_skill(tmp_path):
    proc = subprocess.run(
        [sys.executable, str(REPO / "recipes" / "diayn.py"), "num_skills=1", "logger.backend=none",
         f"output_dir={tmp_path}"],
        check=False, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode != 0
    assert "num_skills: got 1; expected an integer >= 2" in proc.stderr


def test_coverage_metrics_on_known_points():
    from umrl.skill_coverage import convex_hull_area, coverage_metrics, final_states

    square = torch.tensor([[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0], [1.0, 1.0]])
    assert convex_hull_area(square) == pytest.approx(4.0)
    # two skills, two rollouts each, 3 steps; copy 0 ends early (done at t=1)
    done = torch.tensor([[0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 0, 1]], dtype=torch.bool)[..., None]
    position = torch.arange(4 * 3 * 2, dtype=torch.float32).reshape(4, 3, 2)
    rollout = TensorDict({"next": {"done": done, "position": position, "observation": position}}, [4, 3])
    result = final_states(rollout, "point_nav")
    torch.testing.assert_close(result["end_point"], position[[0, 1, 2, 3], [1, 2, 2, 2]])
    result.set("skill", torch.tensor([0, 1, 0, 1]))
    metrics = coverage_metrics(result, 2)
    assert metrics["centroid_hull_area"] == 0.0 and metrics["centroid_pairwise_distance"] > 0
    assert "task_distance_median" not in metrics
    # per-skill std of the end points: (7, 7) for skill 0 and (6, 6) for skill 1, their norms averaged
    assert metrics["within_skill_std"] == pytest.approx((7 + 6) * 2**0.5 / 2)
    # centroids: skill 0 (2, 3) and (16, 17) -> (9, 10); skill 1 (10, 11) and (22, 23) -> (16, 17)
    tasks = torch.tensor([[9.0, 13.0], [16.0, 17.0], [0.0, 10.0]])  # nearest centroid 3, 0 and 9 away
    metrics = coverage_metrics(result, 2, eval_tasks=tasks)
    assert metrics["task_distance_median"] == pytest.approx(3.0)
    assert metrics["task_distance_max"] == pytest.approx(9.0)
    velocity = TensorDict({"next": {"done": done, "x_velocity": position[..., :1], "observation": position}}, [4, 3])
    torch.testing.assert_close(final_states(velocity, "half_cheetah")["end_point"][0], position[0, :2, :1].mean(0))
