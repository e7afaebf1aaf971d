"""Meta-test results: tidy rows round trip, curves and the summary table, both SGD schedules side by side, the
ablation table, the pre-training note, the summary's provenance section, and figures that leave matplotlib's backend
alone."""
import subprocess
import sys

import numpy as np
import pytest

from umrl.metatest import (
    ablation_curves,
    ablation_table,
    arm_label,
    arm_styles,
    baseline_arms,
    curves_from_rows,
    pretraining_note,
    provenance,
    read_rows,
    suite_summary,
    summary_table,
    to_rows,
    write_rows,
)

#: mean episode lengths [K + 1, T] of episodes that all run to the horizon (100 steps)
FULL_6x4, FULL_3x2 = np.full((6, 4), 100.0), np.full((3, 2), 100.0)


def test_tidy_rows_roundtrip_curves_and_table(tmp_path):
    rows = []
    for seed in range(2):
        good = np.tile(np.arange(6.0)[:, None], (1, 4))  # [K+1=6, T=4], rising
        rows += to_rows(good + seed, FULL_6x4, method="uml_diayn", env="point_nav", seed=seed)
        rows += to_rows(np.zeros((6, 4)), FULL_6x4, method="scratch", env="point_nav", seed=seed)
    path = write_rows(rows, tmp_path / "cell.csv")
    back = read_rows([path])
    assert back == rows
    curves = curves_from_rows(back)
    np.testing.assert_allclose(curves["point_nav"]["uml_diayn"].mean, np.arange(6.0) + 0.5)
    np.testing.assert_allclose(curves["point_nav"]["scratch"].high, 0.0)
    markdown, records = summary_table(back, methods=["uml_diayn", "scratch"])
    assert "| uml_diayn |" in markdown and "k=5" in markdown and markdown.index("uml_diayn") < markdown.index("scratch")
    assert "episode length" not in markdown  # every episode ran to the horizon: no length column
    auc_rec = {r["method"]: r for r in records if r["metric"] == "auc"}
    assert auc_rec["uml_diayn"]["mean"] == pytest.approx(12.5 + 5 * 0.5)  # trapezoid of 0..5 plus the seed offset
    assert auc_rec["scratch"]["mean"] == 0.0


def test_summary_shows_episode_lengths_where_episodes_end_early():
    """On an env that ends episodes early a return sums fewer steps: the table then gives the mean length at k=0, K."""
    lengths = np.array([[30.0, 50.0], [40.0, 60.0], [100.0, 100.0]])  # [K+1=3, T=2]
    rows = to_rows(np.full((3, 2), -1.0), lengths, method="oracle", env="ant", seed=0)
    rows += to_rows(np.full((3, 2), -2.0), FULL_3x2, method="scratch", env="ant", seed=0)
    markdown, records = summary_table(rows, steps=(0,), methods=["oracle", "scratch"])
    assert "episode length k=0 / k=2 (mean)" in markdown
    assert "| 2 | 40.0 / 100.0 |" in markdown and "| 2 | 100.0 / 100.0 |" in markdown
    length_means = {(r["method"], r["metric"]): r["mean"] for r in records if r["metric"].startswith("length")}
    assert length_means == {("oracle", "length_k0"): 40.0, ("oracle", "length_k2"): 100.0,
                            ("scratch", "length_k0"): 100.0, ("scratch", "length_k2"): 100.0}
    with pytest.raises(ValueError, match="lengths .* must match returns"):
        to_rows(np.zeros((3, 2)), np.zeros((2, 2)), method="oracle", env="ant", seed=0)


def test_rows_with_and_without_length_share_one_csv(tmp_path):
    """A cell written before the length column beside a new one: both round-trip, the old rows without a length."""
    new = to_rows(np.full((1, 1), -3.0), np.full((1, 1), 42.0), method="scratch", env="ant", seed=1)
    old = [{k: v for k, v in row.items() if k != "length"} for row in to_rows(
        np.full((1, 1), -2.0), np.full((1, 1), 100.0), method="scratch", env="ant", seed=0)]
    assert read_rows([write_rows(old + new, tmp_path / "mixed.csv")]) == old + new


def test_old_csv_without_schedule_column_reads_as_constant(tmp_path):
    path = tmp_path / "old.csv"
    path.write_text("method,env,seed,task,step,return\nscratch,point_nav,0,0,0,-1.5\n")
    assert read_rows([path]) == [{"method": "scratch", "env": "point_nav", "seed": 0, "task": 0, "step": 0,
                                  "return": -1.5, "lr_schedule": "constant"}]


def test_both_sgd_schedules_are_separate_arms():
    rows = []
    for seed in range(2):
        rows += to_rows(np.full((3, 2), -10.0), FULL_3x2,
                        method="uml_diayn", env="point_nav", seed=seed, lr_schedule="constant")
        rows += to_rows(np.full((3, 2), -4.0), FULL_3x2,
                        method="uml_diayn", env="point_nav", seed=seed)
        rows += to_rows(np.full((3, 2), -7.0), FULL_3x2,
                        method="scratch", env="point_nav", seed=seed)
    markdown, records = summary_table(rows, steps=(0,), methods=["scratch", "uml_diayn"])
    auc_mean = {r["method"]: r["mean"] for r in records if r["metric"] == "auc"}
    # trapezoid over k = 0..2 of a constant r is 2 r, per arm
    # the reference schedule is the SGD methods' default: their arm is named after the method alone
    assert auc_mean == {"scratch": pytest.approx(-14.0), "uml_diayn": pytest.approx(-8.0),
                        "uml_diayn (constant)": pytest.approx(-20.0)}
    lines = [line for line in markdown.splitlines() if line.startswith("| ") and "method" not in line]
    assert [line.split(" | ")[0] for line in lines] == ["| scratch", "| uml_diayn", "| uml_diayn (constant)"]
    assert all(line.endswith("| 4 |") for line in lines)  # 2 seeds x 2 tasks per arm, never mixed
    curves = curves_from_rows(rows)
    assert list(curves["point_nav"]) == ["scratch", "uml_diayn", "uml_diayn (constant)"]
    styles = arm_styles(rows)
    assert styles["uml_diayn"]["color"] == styles["uml_diayn (constant)"]["color"]
    assert styles["uml_diayn (constant)"]["linestyle"] == "--" and styles["uml_diayn"]["linestyle"] == "-"
    assert arm_label("oracle") == "oracle" and arm_label("oracle", "constant") == "oracle (constant)"
    assert arm_label("oracle", "reference") == "oracle" and arm_label("scratch", "constant") == "scratch"


def test_ablation_curves_and_table():
    rows = []
    for it, level in ((0, -10.0), (5, -4.0)):
        rows += to_rows(np.full((3, 2), level), FULL_3x2, method="uml_diayn", env="point_nav", seed=0, iteration=str(it))
    curves = ablation_curves(rows, metric="auc")
    c = curves["point_nav"]["uml_diayn"]
    assert list(c.x) == [0, 5] and c.mean == pytest.approx([-20.0, -8.0])
    table = ablation_table(curves)
    assert "| point_nav | uml_diayn | 0 | -20.0 [-20.0, -20.0] |" in table
    assert "| point_nav | uml_diayn | 5 | -8.0 [-8.0, -8.0] |" in table
    assert ablation_curves(rows, metric="final")["point_nav"]["uml_diayn"].mean == pytest.approx([-10.0, -4.0])
    with pytest.raises(ValueError, match="'auc' or 'final'.*'median'"):
        ablation_curves(rows, metric="median")


def test_a_baseline_without_iterations_is_flat_across_the_checkpoints():
    rows = []
    for it, level in ((0, -10.0), (20, -4.0), (40, -2.0)):
        rows += to_rows(np.full((3, 2), level), FULL_3x2, method="oracle", env="point_nav", seed=0, iteration=str(it))
    rows += to_rows(np.full((3, 2), -6.0), FULL_3x2, method="scratch", env="point_nav", seed=0)
    assert baseline_arms(rows) == {"scratch"}
    curves = ablation_curves(rows, metric="auc")
    scratch = curves["point_nav"]["scratch"]
    assert list(scratch.x) == [0, 40] and scratch.mean == pytest.approx([-12.0, -12.0])
    assert list(curves["point_nav"]["oracle"].x) == [0, 20, 40]
    table = ablation_table(curves, baseline_arms(rows))
    assert "| point_nav | scratch | — | -12.0 [-12.0, -12.0] |" in table
    assert table.count("| scratch |") == 1


def test_pretraining_note_says_shared_or_independent():
    assert "independent" in pretraining_note([0, 1, 2], [0, 1, 2])
    assert "include pre-training variance" in pretraining_note([0, 1, 2], [5, 6, 7])
    shared = pretraining_note([0, 1, 2], [0, 0, 0])
    assert "**shared**" in shared and "0→0, 1→0, 2→0" in shared and "leave out pre-training variance" in shared


def test_summary_records_commit_command_hardware_and_wall_time():
    record = provenance(command="python benchmarks/suite.py profile=quick", wall_seconds=123.4, job_threads=1)
    assert set(record) == {"commit", "command", "cpu", "cores", "torch threads", "gpu", "software", "wall time"}
    sha = record["commit"].removesuffix("-dirty")
    assert len(sha) == 40 and int(sha, 16) >= 0  # this test runs inside the git checkout
    assert record["wall time"] == "123 s" and record["torch threads"].startswith("1 per job")
    markdown = suite_summary("TABLE", profile="quick", pretraining="NOTE", lr_lines=["- lr"], time_lines=["- t"],
                             settings_yaml="a: 1\n", provenance=record, ablation="# Meta-training ablation\n\nX\n")
    assert markdown.index("NOTE") < markdown.index("TABLE") < markdown.index("## Provenance")
    assert f"- commit: {record['commit']}" in markdown and "- command: python benchmarks/suite.py" in markdown
    assert "## Meta-training ablation" in markdown


def test_figures_leave_the_callers_matplotlib_backend_alone(tmp_path):
    """A notebook's backend stays selected through importing umrl.metatest and drawing figures; pyplot stays out."""
    probe = f"""
import sys
import matplotlib
matplotlib.use("svg")
import numpy as np
import torch
import umrl.metatest
from umrl.skill_coverage import plot_coverage
x = np.arange(3.0)
curves = umrl.metatest.plot_adaptation_curves({{"env": {{"uml_diayn": umrl.metatest.Curve(x, x, x - 1, x + 1)}}}},
                                              {str(tmp_path / "curves.png")!r})
coverage = plot_coverage(torch.randn(10, 2), {str(tmp_path / "coverage.png")!r})
print(matplotlib.get_backend(), curves.is_file(), coverage, "matplotlib.pyplot" in sys.modules)
"""
    out = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["svg", "True", str(tmp_path / "coverage.png"), "False"]
    assert (tmp_path / "curves.png").read_bytes()[:4] == (tmp_path / "coverage.png").read_bytes()[:4] == b"\x89PNG"
