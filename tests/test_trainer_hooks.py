"""The trainers' shared base: construction without I/O, setup once, the hook points in their order, an early
stop by a hook, and DIAYN's load_state_dict restoring a whole run."""
import pytest
import torch

from umrl.trainers import DIAYNTrainer, MAMLTrainer, VIMETrainer, compose
from umrl.trainers.base import HOOK_POINTS, Trainer

MAML_TINY = ["proposal=random", "env.horizon=8", "meta_batch_size=2", "trajectories_per_task=2",
             "policy.hidden=[8]", "num_skills=3", "progress=false", "trpo.cg_iters=3"]
VIME_TINY = ["env.name=point_nav", "env.num_envs=4", "env.horizon=10", "policy.hidden=[8]",
             "dynamics.hidden=[8]", "dynamics.updates_per_iteration=2", "dynamics.batch_size=8",
             "logger.backend=none", "progress=false", "iterations=1"]
DIAYN_TINY = ["env.name=point_nav", "num_skills=3", "env.horizon=10", "env.num_envs=2", "network.hidden=[16]",
              "network.discriminator_hidden=[16]", "replay_buffer.batch_size=8",
              "collector.init_random_frames=8", "collector.frames_per_batch=4", "log_every=8",
              "eval.every=1000", "eval.episodes_per_skill=1", "logger.backend=none", "progress=false"]


def files(folder) -> list[str]:
    return sorted(str(path.relative_to(folder)) for path in folder.rglob("*") if path.is_file())


def recorder(trainer: Trainer) -> list[tuple]:
    """Register an op on every hook point of ``trainer`` that appends ``(point, *what it was given)`` to the
    list returned (metrics as their sorted keys)."""
    calls = []
    for point in HOOK_POINTS:
        def op(t, *args, point=point):
            assert t is trainer
            calls.append((point, *(tuple(sorted(a)) if isinstance(a, dict) else a for a in args)))
        trainer.register_op(point, op)
    return calls


def test_construction_does_no_io_and_setup_runs_once(tmp_path):
    trainer = MAMLTrainer(compose("maml", [*MAML_TINY, "logger.backend=csv", "iterations=1",
                                           f"output_dir={tmp_path}"]))
    assert files(tmp_path) == ["run.lock"] and trainer.logger is None and not trainer.is_set_up
    trainer.setup()
    written = files(tmp_path)
    assert "checkpoints/step_0.safetensors" in written and any(name.startswith("csv/") for name in written)
    trainer.setup()  # once only
    assert files(tmp_path) == written
    trainer.close()

    diayn = DIAYNTrainer(compose("diayn", [*DIAYN_TINY, "collector.total_frames=16",
                                           f"output_dir={tmp_path / 'diayn'}"]))
    assert files(tmp_path / "diayn") == ["run.lock"] and diayn.baseline is None and not diayn.random_metrics
    calls = recorder(diayn)
    diayn.step()  # the first step sets up: the random policy's rollouts and its scores, logged once
    assert diayn.baseline is not None and diayn.random_metrics
    assert calls[:3] == [("post_log", tuple(sorted(diayn.random_metrics))), ("setup",), ("pre_step",)]
    diayn.close()


def test_hook_points_run_in_order_around_the_loop(tmp_path):
    trainer = MAMLTrainer(compose("maml", [*MAML_TINY, "logger.backend=none", "iterations=2",
                                           "checkpoint.every=1", f"output_dir={tmp_path}"]))
    calls = recorder(trainer)
    result = trainer.train()
    trainer.close()
    checkpoints = trainer.checkpointer.all()
    metric_keys = tuple(sorted(k for k in result if k not in ("iteration", "checkpoint")))
    phases = [("pre_phase", "collect"), ("post_phase", "collect"), ("pre_phase", "inner_step"),
              ("post_phase", "inner_step"), ("pre_phase", "collect"), ("post_phase", "collect"),
              ("pre_phase", "meta_step"), ("post_phase", "meta_step")]
    step = [("pre_step",), *phases, ("post_step", metric_keys), ("post_log", metric_keys)]
    assert calls == [("post_save", checkpoints[0]), ("setup",),  # checkpoint 0, then the logger
                     *step, ("post_save", checkpoints[1]), *step, ("post_save", checkpoints[2]),
                     ("post_evaluate", ()), ("shutdown",)]
    assert result["iteration"] == 2 and result["checkpoint"] == str(checkpoints[2])


def test_a_hook_stops_training_early_after_saving_the_step(tmp_path):
    trainer = VIMETrainer(compose("vime", [*VIME_TINY, "iterations=5", "checkpoint.every=100",
                                           f"output_dir={tmp_path}"]))
    seconds = {}

    def start(t, name):
        seconds[name] = seconds.get(name, 0.0) - 1.0

    def stop(t, name):
        seconds[name] += 1.0

    trainer.register_op("pre_phase", start)
    trainer.register_op("post_phase", stop)
    trainer.register_op("post_step", lambda t, metrics: t.progress == 2 and t.request_stop("enough coverage"))
    result = trainer.train()
    trainer.close()
    assert result["stopped"] == "enough coverage" and trainer.progress == 2 and not trainer.done
    assert [path.name for path in trainer.checkpointer.all()] == ["step_2.safetensors"]  # saved off schedule
    assert result["checkpoint"].endswith("step_2.safetensors")
    assert sorted(seconds) == sorted(VIMETrainer.PHASES) and all(s == 0.0 for s in seconds.values())  # paired


def test_post_phase_runs_when_the_phase_raises_and_bad_registrations_are_refused(tmp_path):
    trainer = VIMETrainer(compose("vime", [*VIME_TINY, f"output_dir={tmp_path}"]))
    calls = recorder(trainer)
    with pytest.raises(RuntimeError, match="inside"), trainer.phase("collect"):
        raise RuntimeError("inside")
    assert calls == [("pre_phase", "collect"), ("post_phase", "collect")]
    with pytest.raises(ValueError, match=r"unknown hook point 'post_epoch'; accepted: \['setup', 'pre_step'"):
        trainer.register_op("post_epoch", print)
    with pytest.raises(TypeError, match="expected a callable"):
        trainer.register_op("post_step", "print")
    trainer.close()


def test_diayn_load_state_dict_continues_the_run_bit_for_bit(tmp_path):
    """A fresh trainer given another's state_dict continues as that run does after a save (the episodes
    restart)."""
    def trainer(name):
        return DIAYNTrainer(compose("diayn", [*DIAYN_TINY, "collector.total_frames=40",
                                              f"output_dir={tmp_path / name}"]))

    continued = trainer("continued")
    for _ in range(3):
        continued.step()
    continued.save()
    for _ in range(3):
        continued.step()
    first = trainer("first")
    for _ in range(3):
        first.step()
    state = first.state_dict()  # what save() writes
    first.close()
    second = trainer("second")
    second.load_state_dict(state)
    for _ in range(3):
        second.step()
    assert second.counters == continued.counters and second.counters["updates"] > 0
    for key, value in continued.loss.state_dict().items():
        assert torch.equal(value, second.loss.state_dict()[key]), key
    continued.close()
    second.close()


def test_diayn_steps_run_their_collect_and_update_phases(tmp_path):
    trainer = DIAYNTrainer(compose("diayn", [*DIAYN_TINY, "collector.total_frames=16",
                                             f"output_dir={tmp_path}"]))
    phases = []
    trainer.register_op("pre_phase", lambda t, name: phases.append(("pre", name)))
    trainer.register_op("post_phase", lambda t, name: phases.append(("post", name)))
    for _ in range(3):  # 4 frames each: updates start once the replay holds the warm-up's 8
        trainer.step()
    trainer.close()
    collect, update = [("pre", "collect"), ("post", "collect")], [("pre", "update"), ("post", "update")]
    assert phases == collect + (collect + update) * 2
