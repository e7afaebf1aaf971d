"""scripts/diagnostics/compare_runs.py: one arm from each of several results files, AUC per horizon, one figure."""
import runpy
import sys
from pathlib import Path

import numpy as np
import pytest

from umrl.metatest import to_rows, write_rows

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "diagnostics" / "compare_runs.py"


def _cli(monkeypatch, capsys, *args):
    monkeypatch.setattr(sys, "argv", ["compare_runs.py", *args])
    runpy.run_path(str(SCRIPT), run_name="__main__")
    return capsys.readouterr().out


def _table(printed):
    """The first table's rows by run label."""
    first = printed.split("\n\n")[1]
    return {line.strip("| ").split(" | ")[0]: line.strip("| ").split(" | ")
            for line in first.splitlines() if not line.startswith(("| run ", "|---"))}


@pytest.fixture
def two_runs(tmp_path):
    """Run ``short`` (K = 4, ``uml_random`` with the constant schedule, an arm suffixed by it, and scratch) and run
    ``long`` (K = 8, two seeds, the second's returns twice the first's)."""
    k4, k8 = np.arange(5.0)[:, None], np.arange(9.0)[:, None]
    tasks = np.arange(4.0)[None, :]
    short = to_rows(-(10.0 - k4) * (1 + tasks), np.full((5, 4), 100.0), method="uml_random", env="point_nav", seed=0,
                    lr_schedule="constant")
    short += to_rows(-np.ones((5, 4)), np.full((5, 4), 100.0), method="scratch", env="point_nav", seed=0)
    long = [row for seed in (0, 1) for row in to_rows(-(10.0 - k8) * (1 + tasks) * (1 + seed), np.full((9, 4), 100.0),
                                                      method="uml_random", env="point_nav", seed=seed,
                                                      lr_schedule="constant")]
    write_rows(short, tmp_path / "short" / "results.csv")
    write_rows(long, tmp_path / "long.csv")
    return tmp_path


def test_prints_iqm_auc_per_horizon_and_draws_a_panel_per_horizon(two_runs, monkeypatch, capsys):
    out = two_runs / "curves.png"
    printed = _cli(monkeypatch, capsys, "--horizons", "4", "8", "--steps", "0", "6", "--out", str(out),
                   "--run", f"short=uml_random (constant)@{two_runs / 'short'}",
                   "--run", f"long=uml_random (constant)@{two_runs / 'long.csv'}",
                   "--run", f"scratch=scratch@{two_runs / 'short' / 'results.csv'}")
    rows = _table(printed)
    # task t's curve is -(10 - k)(1 + t): AUC over k = 0..4 is -(1 + t) * 32, over k = 0..8 -(1 + t) * 48; the IQM of
    # four tasks averages the middle two (t = 1, 2)
    assert rows["short"] == ["short", "uml_random (constant)", "4", "-25.0", "—", rows["short"][5], "—"]
    assert rows["short"][5].startswith("-80.0 [")
    # long's 8 runs (2 seeds x 4 tasks): the IQM averages the middle four values
    assert rows["long"][2:5] == ["8", "-32.5", "-13.0"]
    assert rows["long"][5].startswith("-104.0 [") and rows["long"][6].startswith("-156.0 [")
    # each seed's mean curve over tasks is 2.5 (seed 0) or 5 (seed 1) times -(10 - k)
    seeds = next(line for line in printed.splitlines() if line.startswith("| long | 0 / 1"))
    assert seeds.strip("| ").split(" | ")[2:] == ["-80.0 / -160.0", "-120.0 / -240.0"]
    assert rows["scratch"][3] == "-1.0" and rows["scratch"][5] == "-4.0 [-4.0, -4.0]" and rows["scratch"][6] == "—"
    assert out.stat().st_size > 1000 and f"figure: {out}" in printed


@pytest.mark.parametrize("spec, message", [
    ("no-separators", "expected LABEL=ARM@PATH"),
    ("x=scratch@/nowhere/results.csv", "neither a results.csv nor a folder"),
    ("x=uml_diayn@{dir}/long.csv", "no arm 'uml_diayn' on env 'point_nav'; it has 'uml_random \\(constant\\)'"),
])
def test_bad_run_specs_are_refused_with_what_is_accepted(two_runs, monkeypatch, capsys, spec, message):
    with pytest.raises(SystemExit, match=message):
        _cli(monkeypatch, capsys, "--run", spec.format(dir=two_runs))


def test_bad_horizons_and_duplicate_labels_are_refused(two_runs, monkeypatch, capsys):
    run = f"a=scratch@{two_runs / 'short'}"
    with pytest.raises(SystemExit, match=r"--horizons: got \[0\]; expected integers >= 1"):
        _cli(monkeypatch, capsys, "--horizons", "0", "--run", run)
    with pytest.raises(SystemExit, match="labels must differ"):
        _cli(monkeypatch, capsys, "--run", run, "--run", run)


def test_paired_compares_each_later_run_with_the_first_task_by_task(two_runs, monkeypatch, capsys):
    printed = _cli(monkeypatch, capsys, "--paired", "--horizons", "4", "8",
                   "--run", f"short=uml_random (constant)@{two_runs / 'short'}",
                   "--run", f"long=uml_random (constant)@{two_runs / 'long.csv'}",
                   "--run", f"scratch=scratch@{two_runs / 'short'}")
    paired = {line.strip("| ").split(" | ")[0]: line.strip("| ").split(" | ")
              for line in printed.split("\n\n")[3].splitlines() if not line.startswith(("| run ", "|---"))}
    # seed 0 only is shared; long's seed 0 equals short on k = 0..4, so every task's difference is 0 and none is ahead
    assert paired["long"] == ["long", "4", "0.0 [0.0, 0.0], 0", "—"]
    # scratch's AUC over k = 0..4 is -4 on every task, short's -32 (1 + t): differences 28, 60, 92, 124, all ahead
    assert paired["scratch"] == ["scratch", "4", paired["scratch"][2], "—"]
    assert paired["scratch"][2].startswith("76.0 [") and paired["scratch"][2].endswith("], 4")


def test_paired_refuses_runs_without_a_shared_seed(two_runs, monkeypatch, capsys):
    only_seed_1 = two_runs / "seed1.csv"
    rows = (two_runs / "long.csv").read_text().splitlines()
    only_seed_1.write_text("\n".join([rows[0]] + [r for r in rows[1:] if r.split(",")[2] == "1"]) + "\n")
    with pytest.raises(SystemExit, match=r"--paired: 'b' and 'a' share no seed with the same tasks \(seeds \[1\] and \[0\]\)"):
        _cli(monkeypatch, capsys, "--paired", "--horizons", "4", "--run", f"a=scratch@{two_runs / 'short'}",
             "--run", f"b=uml_random (constant)@{only_seed_1}")


def test_a_glob_path_pools_the_files_it_matches_as_one_run(two_runs, monkeypatch, capsys):
    rows = (two_runs / "long.csv").read_text().splitlines()
    for seed in ("0", "1"):
        folder = two_runs / f"seed{seed}"
        folder.mkdir()
        (folder / "cells.csv").write_text("\n".join([rows[0]] + [r for r in rows[1:] if r.split(",")[2] == seed]) + "\n")
    pooled = _table(_cli(monkeypatch, capsys, "--horizons", "8", "--steps", "0",
                         "--run", f"split=uml_random (constant)@{two_runs}/seed*/cells.csv",
                         "--run", f"whole=uml_random (constant)@{two_runs / 'long.csv'}"))
    assert pooled["split"][1:] == pooled["whole"][1:] and pooled["split"][2] == "8"
    with pytest.raises(SystemExit, match=r"matches no file \(or a folder\)"):
        _cli(monkeypatch, capsys, "--run", f"x=scratch@{two_runs}/nothing*/cells.csv")
