"""docs/fidelity.md's citations point at live code, and every row of its tables names its reference.

A code citation is ``path:LINE`` in backticks followed by `` (`symbol`) ``, with ``path`` a file of this repository
under ``umrl/``, ``benchmarks/`` or ``recipes/``: ``symbol`` must occur on line LINE or on one of the
:data:`WINDOW` lines after it, so a citation cannot drift silently when code moves. A reference citation is a
path with a line after ``D``, ``M`` or ``V`` (ben-eysenbach/sac, cbfinn/maml_rl, openai/vime), or the paper (``P App. C``,
``P §4``); a row without one says ``(no reference counterpart: ...)``.
"""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "fidelity.md"
WINDOW = 3
CODE_PATH = r"(?:umrl|benchmarks|recipes)/[\w./-]+"
CITATION = re.compile(rf"`({CODE_PATH}):(\d+)` \(`([^`]+)`\)")
ANY_CODE_LINE = re.compile(rf"`{CODE_PATH}:\d+`")
REFERENCE = re.compile(r"\b[DMV] `[\w./-]+:\d+`|`P (?:App\. [A-Z]|§\d+)`")
NO_COUNTERPART = "(no reference counterpart: "


def page_text() -> str:
    return PAGE.read_text(encoding="utf-8")


def table_rows(text: str) -> list[str]:
    """The body rows of every Markdown table (each table's header and separator lines skipped)."""
    rows, table = [], []
    for line in [*text.splitlines(), ""]:
        if line.startswith("|"):
            table.append(line)
            continue
        rows.extend(table[2:])
        table = []
    return rows


CITATIONS = CITATION.findall(page_text())


def test_page_has_code_citations():
    assert len(CITATIONS) >= 50, f"found {len(CITATIONS)} code citations in {PAGE}"


@pytest.mark.parametrize(("path", "line", "symbol"), CITATIONS, ids=[f"{p}:{n}" for p, n, _ in CITATIONS])
def test_code_citation_points_at_its_symbol(path, line, symbol):
    source = ROOT / path
    assert source.is_file(), f"{path} (cited in docs/fidelity.md) does not exist"
    lines = source.read_text(encoding="utf-8").splitlines()
    first = int(line)
    window = lines[first - 1: first + WINDOW]
    found = [i + 1 for i, text in enumerate(lines) if symbol in text]
    assert any(symbol in text for text in window), (
        f"docs/fidelity.md cites {path}:{line} for {symbol!r}, which is not on lines {first}..{first + WINDOW}; "
        f"it occurs on lines {found or 'none'}")


def test_every_code_line_names_its_symbol():
    bare = [m.group(0) for m in ANY_CODE_LINE.finditer(page_text())
            if not CITATION.match(page_text(), m.start())]
    assert not bare, f"code citations without a (`symbol`): {bare}"


def test_every_row_cites_its_reference():
    rows = table_rows(page_text())
    assert len(rows) >= 40, f"found {len(rows)} table rows in {PAGE}"
    missing = [row.split("|")[1].strip() for row in rows
               if not REFERENCE.search(row) and NO_COUNTERPART not in row]
    assert not missing, f"rows with neither a reference citation nor {NO_COUNTERPART!r}...: {missing}"


def test_every_row_cites_umrl_code():
    missing = [row.split("|")[1].strip() for row in table_rows(page_text()) if not CITATION.search(row)]
    assert not missing, f"rows without a code citation: {missing}"
