"""A meta-test cell counts as finished only when its file is a regular file of the cell's own settings, as written.

Anything else at a cell's ``output`` (a CSV of another K, other tasks or another method, one cut short, one an older
umrl wrote without its settings) is named in one warning line and recomputed; a folder or a FIFO there is refused
before any work."""
import dataclasses
import json
import os
import warnings

import pytest

from umrl.metatest import AdaptationConfig, CellSpec, read_rows, run_cell
from umrl.validation import InvalidValue

PROTOCOL = AdaptationConfig(num_steps=1, num_trajectories=2, horizon=5)


def scratch_cell(tmp_path, **changes) -> CellSpec:
    spec = CellSpec(method="scratch", env="point_nav", seed=0, output=str(tmp_path / "cell.csv"), num_tasks=2,
                    protocol=PROTOCOL)
    return dataclasses.replace(spec, **changes)


def run_quietly(spec: CellSpec) -> list[dict]:
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a finished cell of these settings: no warning
        return read_rows([run_cell(spec)])


@pytest.mark.parametrize("changes, key", [
    ({"protocol": dataclasses.replace(PROTOCOL, num_steps=2)}, "protocol.num_steps: 2, now 1"),
    ({"num_tasks": 3}, "num_tasks: 3, now 2"),
    ({"method": "vime_init", "checkpoint": "run"}, "method: 'vime_init', now 'scratch'"),
])
def test_a_cell_file_of_other_settings_is_named_and_recomputed(tmp_path, changes, key):
    other = scratch_cell(tmp_path, **changes)
    cell = scratch_cell(tmp_path)
    if other.method == "scratch":
        run_cell(other)
    else:  # a vime_init cell's files, without pre-training a VIME run: its JSON records its settings
        run_cell(cell)
        info_path = tmp_path / "cell.json"
        info_path.write_text(json.dumps({**json.loads(info_path.read_text()), "settings": other.settings()}))
    with pytest.warns(UserWarning, match=rf"recomputing the cell {cell.output}: written with other settings \(.*{key}"):
        rows = read_rows([run_cell(cell)])
    assert {(r["method"], r["task"], r["step"]) for r in rows} == {("scratch", t, k) for t in (0, 1) for k in (0, 1)}
    assert run_quietly(cell) == rows


@pytest.mark.parametrize("cut", ["a row", "a number"])
def test_a_truncated_cell_csv_is_named_and_recomputed(tmp_path, cut):
    cell = scratch_cell(tmp_path)
    complete = run_quietly(cell)
    with open(cell.output, newline="") as f:
        text = f.read()
    end = text.rindex("\r\n", 0, len(text) - 2) + 2 if cut == "a row" else text.rindex(".") + 2
    with open(cell.output, "w", newline="") as f:
        f.write(text[:end])  # a cut at a row's end reads as a table: only the record of what was written tells
    with pytest.warns(UserWarning, match=rf"recomputing the cell {cell.output}: the CSV is not the one its cell.json "
                                         r"records \(cut short or edited\)"):
        assert read_rows([run_cell(cell)]) == complete


def test_a_cell_file_an_older_umrl_wrote_is_named_and_recomputed(tmp_path):
    cell = scratch_cell(tmp_path)
    run_quietly(cell)
    info_path = tmp_path / "cell.json"
    info = json.loads(info_path.read_text())
    info_path.write_text(json.dumps({k: v for k, v in info.items() if k not in ("settings", "csv_sha256")}))
    with pytest.warns(UserWarning, match=rf"recomputing the cell {cell.output}: {info_path} records no settings"):
        run_cell(cell)
    (tmp_path / "cell.json").unlink()
    with pytest.warns(UserWarning, match=rf"recomputing the cell {cell.output}: no cell.json beside it"):
        run_cell(cell)
    run_quietly(cell)


def test_a_recorded_checkpoint_is_relative_so_a_moved_cell_stays_finished(tiny_maml_run, tmp_path):
    """The settings name the checkpoint relative to the cell: results moved with their run are still finished."""
    import shutil

    cell = CellSpec(method="oracle", env="point_nav", seed=0, output=str(tmp_path / "a" / "cells" / "cell.csv"),
                    checkpoint=str(tmp_path / "a" / "run"), num_tasks=2, protocol=PROTOCOL)
    shutil.copytree(tiny_maml_run, cell.checkpoint)
    rows = run_quietly(cell)
    os.rename(tmp_path / "a", tmp_path / "b")
    moved = dataclasses.replace(cell, output=str(tmp_path / "b" / "cells" / "cell.csv"),
                                checkpoint=str(tmp_path / "b" / "run"))
    mtime = os.stat(moved.output).st_mtime_ns
    assert run_quietly(moved) == rows and os.stat(moved.output).st_mtime_ns == mtime


@pytest.mark.parametrize("make, kind", [(os.mkdir, "a folder"), (os.mkfifo, "a special file")])
@pytest.mark.parametrize("which", ["csv", "json"])
def test_a_folder_or_fifo_at_a_cells_output_is_refused_before_any_work(tmp_path, make, kind, which):
    cell = scratch_cell(tmp_path, method="uml_diayn", checkpoint=str(tmp_path / "no_run"))  # loading it would fail
    make(tmp_path / f"cell.{which}")
    with pytest.raises(InvalidValue, match=rf"output: got '{cell.output}' \({tmp_path}/cell.{which} is {kind}.*\); "
                                           r"expected a path where the cell's CSV and the .json beside it are "
                                           "regular files or absent"):
        run_cell(cell)
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"cell.{which}"]


def test_a_cell_in_a_folder_it_cannot_write_is_refused_before_any_work(tmp_path):
    (tmp_path / "afile").write_text("not a folder")
    cell = scratch_cell(tmp_path, method="uml_diayn", checkpoint=str(tmp_path / "no_run"),
                        output=str(tmp_path / "afile" / "cell.csv"))
    with pytest.raises(InvalidValue, match=rf"output's folder: got '{tmp_path}/afile' \(a file\); expected a "
                                           "writable directory"):
        run_cell(cell)
