"""Exporting a suite's cells into the results layout (:mod:`umrl.suite.export`)."""
import json

import pytest

from umrl.metatest.provenance import relative_path, resolve_recorded_path
from umrl.suite.export import export_cells, main


def cell(path, checkpoint=None, finished=True):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(f"{path.stem}\n")
    if finished:
        info = {"method": path.parent.name, "checkpoint": checkpoint and relative_path(checkpoint, path)}
        path.with_suffix(".json").write_text(json.dumps(info))


@pytest.fixture
def suite(tmp_path):
    run = tmp_path / "runs" / "oracle" / "seed0"
    run.mkdir(parents=True)
    s = tmp_path / "suite"
    cell(s / "cells/pn/oracle/seed0-0123456789ab.csv", run)
    cell(s / "cells/pn/oracle/seed0.constant-0123456789ab.csv", run)
    cell(s / "cells/pn/scratch/seed1-ba9876543210.csv")
    cell(s / "cells/pn/scratch/seed2-ba9876543210.csv", finished=False)
    cell(s / "cells/ant/scratch/seed0-ba9876543210.csv")
    cell(s / "ablation/pn/oracle/seed0/iter20-0123456789ab.csv", run / "checkpoints" / "step_20.pt")
    cell(s / "ablation/pn/scratch/seed0-0123456789ab.csv")
    return s, run


def test_export_names_and_checkpoints(suite, tmp_path):
    s, run = suite
    dst = tmp_path / "results" / "pn"
    written = export_cells(s, "pn", dst)
    assert sorted(p.relative_to(dst).as_posix() for p in written) == [
        "along_meta_training/seed0/oracle/iter20.csv", "along_meta_training/seed0/scratch.csv",
        "meta_test_ref/seed0/oracle.constant.csv", "meta_test_ref/seed0/oracle.csv", "meta_test_ref/seed1/scratch.csv"]
    copy = dst / "meta_test_ref/seed0/oracle.csv"
    assert copy.read_text() == "seed0-0123456789ab\n"
    recorded = json.loads(copy.with_suffix(".json").read_text())["checkpoint"]
    assert recorded == "../../../../runs/oracle/seed0"
    assert resolve_recorded_path(recorded, copy).resolve() == run.resolve()
    assert json.loads((dst / "meta_test_ref/seed1/scratch.json").read_text())["checkpoint"] is None


def test_export_of_some_methods(suite, tmp_path, capsys):
    s, _ = suite
    main([str(s), "pn", str(tmp_path / "out"), "--methods", "scratch"])
    assert "2 cells exported" in capsys.readouterr().out
    assert sorted(p.name for p in (tmp_path / "out").rglob("*.csv")) == ["scratch.csv", "scratch.csv"]


def test_export_of_the_ablation_alone(suite, tmp_path):
    s, _ = suite
    main([str(s), "pn", str(tmp_path / "out"), "--parts", "ablation"])
    assert sorted(p.relative_to(tmp_path / "out").as_posix() for p in (tmp_path / "out").rglob("*.csv")) == [
        "along_meta_training/seed0/oracle/iter20.csv", "along_meta_training/seed0/scratch.csv"]
    with pytest.raises(ValueError, match=r"parts: got \['cell'\]; expected one or more of \['ablation', 'cells'\]"):
        export_cells(s, "pn", tmp_path / "out2", parts=["cell"])


def test_two_keys_for_one_cell_are_refused_before_copying(suite, tmp_path):
    s, _ = suite
    cell(s / "cells/pn/oracle/seed0-fedcba987654.csv")
    with pytest.raises(ValueError, match=r"seed0-0123456789ab.csv and .*seed0-fedcba987654.csv"):
        export_cells(s, "pn", tmp_path / "out")
    assert not (tmp_path / "out").exists()
