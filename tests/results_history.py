"""The runs that left ``results/`` for git history, as the table of results/README.md's section "In git history"
lists them: ``{folder: commit}``, the folder relative to the repository root (``results/point_nav/oracle_paper``)
and the last commit that changed it (its files are in that commit)."""
import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ROW = re.compile(r"^\| `((?:[\w.-]+/)+)` \|.*\| `([0-9a-f]{7,40})` \|$", re.MULTILINE)


def _listed() -> dict[str, str]:
    text = (REPO / "results" / "README.md").read_text()
    return {f"results/{folder.rstrip('/')}": commit for folder, commit in ROW.findall(text)}


IN_HISTORY = _listed()


def in_history(path: str) -> bool:
    """Whether a repository-relative path (a glob too) lies in a folder that is in git history only."""
    return any(path == folder or path.startswith(f"{folder}/") for folder in IN_HISTORY)
