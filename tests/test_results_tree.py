"""``results/`` holds the runs its README describes, the runs of earlier settings are in git history at the commit
results/README.md names, and the tracked tree stays under 64 MiB (a quick clone; the most a GPU machine takes)."""
import re
import shutil
import subprocess

import pytest
from doc_commands import spell_out
from results_history import IN_HISTORY, REPO

TREE_LIMIT = 64 * 2**20
"""Bytes: the most the working tree may hold to travel to a GPU machine."""


def _git(*args: str, stdin: str | None = None) -> str:
    return subprocess.run(["git", "-C", str(REPO), *args], input=stdin, capture_output=True, text=True,
                          check=True).stdout


def _needs_git() -> None:
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.skip("not a git checkout: the tracked tree and the history are read with git")


def _run_folders() -> set[str]:
    """``<env>/<run>`` of every run folder under results/."""
    return {f"{p.parent.name}/{p.name}" for p in (REPO / "results").glob("*/*") if p.is_dir()}


def _described_runs() -> set[str]:
    """``<env>/<run>`` of every run a section heading of results/README.md names (shell braces spelled out)."""
    text = (REPO / "results" / "README.md").read_text()
    named = [path for heading in re.findall(r"^## (.*)$", text, flags=re.MULTILINE)
             for path in re.findall(r"`([^`]+)`", heading)]
    spelled = [p for path in named for p in spell_out(path, r"\{([^{}]*,[^{}]*)\}", ",")]
    return {"/".join(p.split("/")[:2]) for p in spelled}


def test_every_run_folder_has_a_section_and_every_section_a_folder():
    folders, described = _run_folders(), _described_runs()
    assert folders, "no run folders under results/"
    assert folders - described == set(), "run folders results/README.md does not describe"
    assert described - folders == set(), "sections of results/README.md whose folder is not in the tree"


def test_runs_in_history_left_the_tree_and_their_commit_holds_them():
    assert IN_HISTORY, "results/README.md lists no runs in git history"
    assert [f for f in IN_HISTORY if (REPO / f).exists()] == []
    _needs_git()
    commits = sorted(set(IN_HISTORY.values()))
    known = _git("cat-file", "--batch-check", stdin="".join(f"{c}^{{commit}}\n" for c in commits))
    if "missing" in known:
        pytest.skip(f"a shallow clone: commits {commits} are not all in it (git fetch --unshallow)")
    kinds = _git("cat-file", "--batch-check=%(objecttype)",
                 stdin="".join(f"{commit}:{folder}\n" for folder, commit in IN_HISTORY.items())).split()
    assert dict(zip(IN_HISTORY, kinds)) == dict.fromkeys(IN_HISTORY, "tree")


def test_the_tracked_tree_stays_under_64_mib():
    _needs_git()
    tracked = [REPO / f for f in _git("ls-files", "-z").split("\0") if f]
    size = sum(p.stat().st_size for p in tracked if p.is_file())  # a deleted file, not yet committed, is gone
    assert size < TREE_LIMIT, f"{size / 2**20:.1f} MiB of tracked files"
