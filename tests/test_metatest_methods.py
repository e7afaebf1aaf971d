"""Method registry (typed records, no string parsing) and the typed cell spec: defaults, validation, run_cell."""
import dataclasses

import pytest

from umrl.metatest import (
    METHODS,
    AdaptationConfig,
    CellSpec,
    Pretraining,
    SweepConfig,
    get_method,
    read_rows,
    run_cell,
)


def test_registry_records_are_typed():
    assert METHODS["uml_diayn"].pretraining == Pretraining("maml", "diayn")
    assert METHODS["uml_diayn"].pretraining.kind == "maml_diayn"
    assert METHODS["uml_diayn"].pretraining.requires == (Pretraining("diayn"),)
    assert METHODS["uml_random"].pretraining.requires == ()
    assert METHODS["diayn_init"].pretraining == Pretraining("diayn") and METHODS["scratch"].pretraining is None
    assert {m.name: m.optimizer for m in METHODS.values()} == {
        "uml_diayn": "sgd", "uml_random": "sgd", "oracle": "sgd",
        "vime_init": "adam", "diayn_init": "adam", "scratch": "adam", "uml_random_arena": "sgd"}
    with pytest.raises(ValueError, match="unknown method 'maml'.*uml_diayn"):
        get_method("maml")
    with pytest.raises(ValueError, match="proposal.*'maml'.*None"):
        Pretraining("maml")
    with pytest.raises(ValueError, match="recipe.*'sac'"):
        Pretraining("sac")


def test_cell_spec_defaults_live_in_the_dataclass():
    spec = CellSpec(method="scratch", env="point_nav", seed=0, output="x.csv")
    assert spec.protocol == AdaptationConfig() and spec.sweep == SweepConfig()
    assert (spec.num_tasks, spec.adam_lr, spec.sgd_lr, spec.skill_trajectories, spec.threads) == (20, 1e-3, None, 4, 1)
    assert spec.lr_schedule == "constant"
    built = CellSpec.from_mapping({"method": "oracle", "env": "point_nav", "seed": 1, "output": "y.csv",
                                   "checkpoint": "run", "protocol": {"num_steps": 3, "sgd_schedule": "reference"},
                                   "sweep": {"enabled": True, "lrs": [1e-3]}})
    assert built.protocol == dataclasses.replace(AdaptationConfig(), num_steps=3, sgd_schedule="reference")
    assert built.sweep.lrs == (1e-3,) and built.sweep.num_tasks == SweepConfig().num_tasks
    assert built.lr_schedule == "reference"
    adam = dataclasses.replace(built, method="vime_init")
    assert adam.lr_schedule == "constant"  # the schedule is SGD's


BASE = {"method": "scratch", "env": "point_nav", "seed": 0, "output": "x.csv"}


@pytest.mark.parametrize("override, key, shown, accepted", [
    ({"method": "uml"}, "method", "'uml'", "one of 'uml_diayn'"),
    ({"env": ""}, "env", "''", "a non-empty string"),
    ({"seed": -1}, "seed", "-1", "an integer >= 0"),
    ({"seed": 1.5}, "seed", "1.5", "an integer >= 0"),
    ({"num_tasks": 0}, "num_tasks", "0", "an integer >= 1"),
    ({"threads": True}, "threads", "True", "an integer >= 1"),
    ({"adam_lr": 0.0}, "adam_lr", "0.0", "a finite number > 0"),
    ({"sgd_lr": -0.1}, "sgd_lr", "-0.1", "a finite number > 0"),
    ({"device": "gpu"}, "device", "'gpu'", "one of 'cpu', 'cuda', 'auto'"),
    ({"checkpoint": "somewhere"}, "checkpoint", "'somewhere'", "null for scratch"),
    ({"method": "oracle"}, "checkpoint", "None", "a pre-training output for 'oracle'"),
    ({"sweep": {"enabled": 1}}, "sweep.enabled", "1", "true or false"),
    ({"sweep": {"lrs": []}}, "sweep.lrs", "[]", "a non-empty list of learning rates > 0"),
    ({"sweep": {"lrs": [1e-3, 0]}}, "sweep.lrs[1]", "0", "a finite number > 0"),
    ({"sweep": {"num_steps": 0}}, "sweep.num_steps", "0", "an integer >= 1"),
    ({"sweep": {"later_factors": []}}, "sweep.later_factors", "[]", "a non-empty list of factors > 0"),
    ({"sweep": {"later_factors": [0.5, -1]}}, "sweep.later_factors[1]", "-1", "a finite number > 0"),
])
def test_cell_spec_rejects_bad_values_naming_key_value_and_accepted(override, key, shown, accepted):
    with pytest.raises((ValueError, TypeError)) as err:
        CellSpec.from_mapping({**BASE, **override})
    assert f"{key}: got {shown}; expected {accepted}" in str(err.value)


def test_cell_spec_rejects_bad_protocol_and_unknown_keys():
    with pytest.raises(ValueError, match=r"protocol.sgd_schedule: got 'alpha/2'; expected one of 'constant', "
                                         r"'reference', 'swept'"):
        CellSpec.from_mapping({**BASE, "protocol": {"sgd_schedule": "alpha/2"}})
    with pytest.raises(ValueError, match=r"protocol.num_steps: got -1; expected an integer >= 0"):
        CellSpec.from_mapping({**BASE, "protocol": {"num_steps": -1}})
    with pytest.raises(ValueError, match=r"unknown keys \['protocol.steps'\].*num_steps"):
        CellSpec.from_mapping({**BASE, "protocol": {"steps": 5}})
    with pytest.raises(ValueError, match=r"unknown keys \['lr'\].*adam_lr"):
        CellSpec.from_mapping({**BASE, "lr": 0.1})
    with pytest.raises(TypeError, match="CellSpec"):
        run_cell(dict(BASE))


def test_run_cell_writes_rows_with_schedule_and_skips_finished(tmp_path):
    spec = CellSpec.from_mapping({**BASE, "output": str(tmp_path / "cell.csv"), "num_tasks": 2,
                                  "protocol": {"num_steps": 1, "num_trajectories": 2, "horizon": 5}})
    rows = read_rows([run_cell(spec)])
    assert len(rows) == 2 * 2 and {r["lr_schedule"] for r in rows} == {"constant"}
    assert all(0 < r["length"] <= 5 for r in rows)  # mean episode length per task, at most the horizon
    mtime = (tmp_path / "cell.csv").stat().st_mtime_ns
    run_cell(spec)
    assert (tmp_path / "cell.csv").stat().st_mtime_ns == mtime


def test_swept_schedule_picks_the_later_factor_on_the_sweep_tasks(tiny_maml_run, tmp_path):
    """A ``swept`` cell adapts each sweep-task trial with one factor, keeps the best mean AUC (recorded with the
    scores), and its evaluation is meta_test's with that factor; the Adam lr sweep stays off."""
    import json

    import numpy as np

    from umrl.envs.tasks import get_task_family
    from umrl.metatest import load_initialisation, meta_test
    from umrl.metatest.protocol import sweep_tasks
    from umrl.metatest.stats import auc

    protocol = {"num_steps": 3, "num_trajectories": 3, "horizon": 10, "sgd_schedule": "swept"}
    spec = CellSpec.from_mapping({"method": "oracle", "env": "point_nav", "seed": 2, "num_tasks": 2,
                                  "checkpoint": str(tiny_maml_run), "output": str(tmp_path / "cell.csv"),
                                  "protocol": protocol,
                                  "sweep": {"later_factors": [0.01, 4.0], "num_tasks": 2, "num_steps": 3}})
    rows = read_rows([run_cell(spec)])
    info = json.loads((tmp_path / "cell.json").read_text())
    init = load_initialisation("oracle", "point_nav", tiny_maml_run, seed=2)
    config = AdaptationConfig(**protocol)
    scores = {}
    for factor in (0.01, 4.0):
        trial, _ = meta_test(init, "point_nav", sweep_tasks("point_nav", 2, 2), lr=init.lr, seed=2,
                             config=dataclasses.replace(config, sgd_later_factor=factor), skill_trajectories=4)
        scores[factor] = float(auc(trial.numpy().T).mean())
    assert info["later_factor_scores"] == {str(f): pytest.approx(v) for f, v in scores.items()}
    chosen = max(scores, key=scores.get)
    assert info["protocol"]["sgd_later_factor"] == chosen and "sweep_scores" not in info
    expected, _ = meta_test(init, "point_nav", get_task_family("point_nav").eval_tasks(2), lr=init.lr, seed=2,
                            config=dataclasses.replace(config, sgd_later_factor=chosen), skill_trajectories=4)
    got = np.array([[r["return"] for r in rows if r["step"] == k] for k in range(4)])
    np.testing.assert_allclose(got, expected.numpy(), rtol=1e-6)
    assert {r["lr_schedule"] for r in rows} == {"swept"}
