"""The verdict rule on synthetic numbers: every label reachable, the boundaries, claims of several parts, cells read
from a results folder, and the committed point_nav cells judged as the results pages say."""
import json
from pathlib import Path

import numpy as np
import pytest

from umrl.metatest import to_rows, write_rows
from umrl.suite.verdicts import (
    CLAIMS,
    GATES,
    Claim,
    ahead,
    claim_verdict,
    close_behind,
    contrast,
    evidence,
    judge,
    load_cells,
    main,
    part_verdict,
    verdict_table,
)

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize(("low", "high", "seed_means", "expected"), [
    (1.0, 3.0, [2.0, 1.0, 0.5], "agrees"),
    (-3.0, -1.0, [-2.0, -0.1], "disagrees"),
    (1.0, 3.0, [2.0, -0.5, 1.0], "partly"),      # pooled ahead, one seed behind
    (-3.0, -1.0, [-2.0, 0.3], "partly"),         # pooled behind, one seed ahead
    (-1.0, 2.0, [1.0, 1.0, 1.0], "undecided"),   # every seed ahead, interval holds 0
    (0.0, 2.0, [1.0], "undecided"),              # an interval touching 0 does not exclude it
    (-2.0, 0.0, [-1.0], "undecided"),
    (1e-9, 2.0, [1.0], "agrees"),
    (1.0, 2.0, [0.0], "partly"),                 # a seed exactly level is not ahead
])
def test_part_verdict_labels_and_boundaries(low, high, seed_means, expected):
    assert part_verdict(low, high, seed_means) == expected


def test_part_verdict_refuses_bad_input():
    with pytest.raises(ValueError, match="at least one seed"):
        part_verdict(1.0, 2.0, [])
    with pytest.raises(ValueError, match="above high"):
        part_verdict(2.0, 1.0, [1.0])


@pytest.mark.parametrize(("parts", "expected"), [
    (["agrees"], "agrees"),
    (["agrees", "agrees", "agrees"], "agrees"),
    (["agrees", "undecided"], "partly"),
    (["agrees", "disagrees"], "partly"),
    (["partly", "disagrees"], "partly"),
    (["partly"], "partly"),
    (["disagrees", "undecided"], "disagrees"),
    (["disagrees"], "disagrees"),
    (["undecided", "undecided"], "undecided"),
])
def test_claim_verdict_combines_parts(parts, expected):
    assert claim_verdict(parts) == expected


def test_claim_verdict_refuses_unknown_labels():
    with pytest.raises(ValueError, match="expected one or more of"):
        claim_verdict(["agrees", "maybe"])
    with pytest.raises(ValueError, match="expected one or more of"):
        claim_verdict([])


def curves(level: np.ndarray, steps: int = 5) -> np.ndarray:
    """``[tasks, steps]`` returns, constant per task at ``level``."""
    return np.repeat(np.asarray(level, dtype=np.float64)[:, None], steps, axis=1)


def test_ahead_contrast_is_the_paired_auc_difference():
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(8, 6)), rng.normal(size=(8, 6))
    values = contrast({"a": {0: a}, "b": {0: b}}, ahead("a", "b"))
    expected = (a[:, 1:] + a[:, :-1]).sum(1) / 2 - (b[:, 1:] + b[:, :-1]).sum(1) / 2
    np.testing.assert_allclose(values[0], expected)


def test_close_behind_is_above_the_midpoint_of_the_leader_and_scratch():
    scratch, oracle = curves(np.full(10, -10.0)), curves(np.full(10, -2.0))
    noise = np.linspace(-0.1, 0.1, 10)
    for level, expected in ((-5.0, "agrees"), (-7.0, "disagrees"), (-6.0, "undecided")):
        per_seed = {"scratch": {0: scratch, 1: scratch}, "oracle": {0: oracle, 1: oracle},
                    "uml_diayn": {0: curves(level + noise), 1: curves(level - noise)}}
        for metric in ("auc", "final"):
            part = close_behind("uml_diayn", "oracle", metric=metric)
            assert evidence(part, contrast(per_seed, part)).verdict == expected, (level, metric)


def test_evidence_pools_seeds_and_keeps_each_seeds_mean():
    per_seed = {"a": {0: curves(np.full(20, 3.0)), 1: curves(np.full(20, -1.0))},
                "b": {0: curves(np.zeros(20)), 1: curves(np.zeros(20))}}
    e = evidence(ahead("a", "b"), contrast(per_seed, ahead("a", "b")))
    assert e.seed_means == {0: 12.0, 1: -4.0}  # AUC over k = 0..4 of a constant is 4 × the level
    assert (e.runs, e.ahead, e.mean) == (40, 20, 4.0)
    assert e.low > 0 and e.verdict == "partly"  # the pooled lead is not repeated on seed 1


def test_contrast_uses_only_seeds_with_every_method_and_refuses_unpaired_cells():
    per_seed = {"a": {0: curves(np.ones(4)), 1: curves(np.ones(4))}, "b": {1: curves(np.zeros(4))}}
    assert list(contrast(per_seed, ahead("a", "b"))) == [1]
    assert contrast(per_seed, ahead("a", "missing")) == {}
    per_seed["b"][0] = curves(np.zeros(5))
    with pytest.raises(ValueError, match="same tasks"):
        contrast(per_seed, ahead("a", "b"))


def test_judge_gates_and_missing_parts():
    claim = Claim("a beats b and c", (ahead("a", "b"), ahead("a", "c")))
    per_seed = {"a": {0: curves(np.linspace(1, 2, 10))}, "b": {0: curves(np.zeros(10))}}
    verdict = judge(claim, "point_nav", per_seed)
    assert verdict.verdict == "partly" and verdict.missing == ("a ahead of c",)  # the part it has agrees
    assert [e.verdict for e in verdict.evidence] == ["agrees"]
    assert judge(claim, "point_nav", {}).verdict == "no cells"
    gated = next(iter(GATES))
    assert judge(claim, gated, per_seed).verdict == "not testable"


def write_cell(root: Path, method: str, seed: int, level: np.ndarray) -> None:
    returns = curves(level).T  # [K + 1, T]
    rows = to_rows(returns, np.full_like(returns, 100.0), method=method, env="point_nav", seed=seed)
    write_rows(rows, root / "point_nav" / "meta_test_ref" / f"seed{seed}" / f"{method}.csv")


def test_verdict_table_from_a_results_folder(tmp_path, capsys):
    tasks = np.linspace(-1.0, 1.0, 10)
    for seed in (0, 1):
        write_cell(tmp_path, "scratch", seed, -10.0 + tasks)
        write_cell(tmp_path, "uml_diayn", seed, -4.0 + tasks)
        write_cell(tmp_path, "uml_random", seed, -14.0 + tasks)
    run = tmp_path / "point_nav" / "uml_diayn_ref" / "seed0" / "checkpoints"  # the budget: from the run's config
    run.mkdir(parents=True)
    (run / "config.yaml").write_text("proposal: diayn\niterations: 50\n")
    cell = tmp_path / "point_nav" / "meta_test_ref" / "seed0" / "uml_diayn.json"
    cell.write_text(json.dumps({"checkpoint": "../../uml_diayn_ref/seed0"}))
    cells = load_cells(tmp_path)
    assert sorted(cells["point_nav"].per_seed) == ["scratch", "uml_diayn", "uml_random"]
    assert cells["point_nav"].budgets == {"MAML": {"50 / 100"}}
    markdown, verdicts = verdict_table(tmp_path)
    by_claim = {v.claim.text: v for v in verdicts if v.env == "point_nav"}
    assert by_claim[CLAIMS[0].text].verdict == "agrees"
    assert by_claim[CLAIMS[1].text].verdict == "disagrees"
    assert by_claim[CLAIMS[2].text].verdict == "no cells"  # no VIME-init, DIAYN-init cells
    assert "+24.0 [24.0, 24.0], seeds 0/1" in markdown  # AUC over k = 0..4: 4 × the 6.0 lead
    assert "| point_nav | 0, 1 | MAML 50 / 100 it. |" in markdown
    main([str(tmp_path), "--figure", str(tmp_path / "verdicts.png")])
    assert capsys.readouterr().out == markdown + f"\nfigure: {tmp_path / 'verdicts.png'}\n"
    assert (tmp_path / "verdicts.png").stat().st_size > 0


def test_cli_names_a_folder_without_cells(tmp_path):
    with pytest.raises(SystemExit, match="no meta-test cells under"):
        main([str(tmp_path)])


def test_committed_point_nav_cells_give_the_pages_verdicts():
    """The labels docs/results/verdicts.md and the README print for point_nav, re-derived from results/."""
    per_seed = load_cells(REPO / "results")["point_nav"].per_seed
    labels = [judge(claim, "point_nav", per_seed).verdict for claim in CLAIMS]
    assert labels == ["undecided", "partly", "partly", "partly"]
    oracle = judge(CLAIMS[3], "point_nav", per_seed).evidence[0]
    assert oracle.short() == "+404.0 [360.1, 447.9]" and oracle.verdict == "agrees"
