"""Result files name the runs they were made from relative to themselves: no machine path, and the name still resolves
after the results and runs are moved together. The committed cells were rewritten that way, nothing else changed."""
import json
import os
import shutil
from pathlib import Path

import pytest
from script_loading import REPO, load_script

from umrl.metatest import AdaptationConfig, CellSpec, run_cell
from umrl.metatest.provenance import relative_path, resolve_recorded_path

rewrite = load_script("scripts/relative_result_paths.py")


def _strings(value):
    if isinstance(value, str):
        yield value
    elif isinstance(value, dict):
        for v in value.values():
            yield from _strings(v)
    elif isinstance(value, list):
        for v in value:
            yield from _strings(v)


def test_a_fresh_cell_records_its_checkpoint_relative_to_itself(tiny_maml_run, tmp_path):
    spec = CellSpec(method="oracle", env="point_nav", seed=0, output=str(tmp_path / "cells" / "oracle.csv"),
                    checkpoint=str(tiny_maml_run), num_tasks=2,
                    protocol=AdaptationConfig(num_steps=1, num_trajectories=2, horizon=5))
    info_path = Path(run_cell(spec)).with_suffix(".json")
    info = json.loads(info_path.read_text())
    assert info["checkpoint"] == "../maml"
    assert not [s for s in _strings(info) if os.path.isabs(s) or str(tmp_path) in s]
    for folder in ("cells", "maml"):  # results and runs moved together
        shutil.copytree(tmp_path / folder, tmp_path / "moved" / folder)
    recorded = resolve_recorded_path(info["checkpoint"], tmp_path / "moved" / "cells" / "oracle.json")
    assert recorded.resolve() == (tmp_path / "moved" / "maml").resolve()


def test_a_relative_checkpoint_argument_is_recorded_relative_to_the_cell(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert relative_path("runs/maml/seed0", "results/pn/meta/seed0/oracle.json") == "../../../../runs/maml/seed0"
    assert relative_path(tmp_path / "a" / "run", tmp_path / "a" / "cell.json") == "run"
    assert resolve_recorded_path("/abs/run", "results/cell.json") == Path("/abs/run")  # older files: kept


def test_no_committed_result_file_holds_an_absolute_machine_path():
    for path in (REPO / "results").rglob("*.json"):
        strings = list(_strings(json.loads(path.read_text())))
        assert not [s for s in strings if s.startswith(("/work/", "/home/", "/tmp/", "/root/", "/Users/"))], path
    for path in (REPO / "results").rglob("*.csv"):
        assert "/work/" not in path.read_text() and "/home/" not in path.read_text(), path


def _cell(tmp_path, name, checkpoint):
    path = tmp_path / "results" / "meta" / "seed0" / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"method": "oracle", "checkpoint": checkpoint, "lr": 0.1, "mean_return": [-1.5, 2.0]},
                               indent=1))
    return path


def test_the_rewrite_changes_only_the_checkpoint_field(tmp_path, capsys):
    old_root = "/somewhere/else/umrl"
    cell = _cell(tmp_path, "oracle.json", f"{old_root}/results/oracle_ref/seed0")
    untouched = _cell(tmp_path, "scratch.json", None)
    before, untouched_text = json.loads(cell.read_text()), untouched.read_text()
    rewrite.main([str(tmp_path / "results"), "--root", old_root])
    assert "1 file(s) rewritten" in capsys.readouterr().out
    after = json.loads(cell.read_text())
    expected = os.path.relpath(REPO / "results" / "oracle_ref" / "seed0", cell.parent)
    assert after == {**before, "checkpoint": expected} and untouched.read_text() == untouched_text
    assert len(cell.read_text().splitlines()) == len(json.dumps(before, indent=1).splitlines())


def test_the_rewrite_refuses_a_path_outside_the_root_and_writes_nothing(tmp_path):
    inside = _cell(tmp_path, "a.json", "/old/umrl/results/x")
    outside = _cell(tmp_path, "b.json", "/elsewhere/x")
    texts = inside.read_text(), outside.read_text()
    with pytest.raises(SystemExit, match=f"{outside}: checkpoint '/elsewhere/x' is outside --root /old/umrl"):
        rewrite.main([str(tmp_path / "results"), "--root", "/old/umrl"])
    assert (inside.read_text(), outside.read_text()) == texts
