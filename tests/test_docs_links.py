"""The docs as a web: every relative link in README.md and docs/ resolves (file and, for a markdown page, heading
anchor), and every page and figure under docs/ is linked from README.md or another docs page."""
import re
import unicodedata
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
SOURCES = [REPO / "README.md", *sorted(DOCS.rglob("*.md"))]
LINK = re.compile(r"!?\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)


def links(page: Path) -> list[str]:
    """Link targets of a markdown page, outside fenced code blocks."""
    return LINK.findall(FENCE.sub("", page.read_text()))


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation and symbols dropped, spaces to hyphens."""
    text = heading.strip().lower()
    kept = "".join(c for c in text if c in " -_" or unicodedata.category(c)[0] in "LNM")
    return kept.replace(" ", "-")


def anchors(page: Path) -> set[str]:
    headings = re.findall(r"^#+\s+(.*)$", FENCE.sub("", page.read_text()), flags=re.MULTILINE)
    return {slug(h.replace("`", "")) for h in headings}


def relative_links() -> list[tuple[Path, str]]:
    return [(page, target) for page in SOURCES for target in links(page)
            if not re.match(r"[a-z]+:", target) and not target.startswith("#")]


@pytest.mark.parametrize("page", SOURCES, ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(page):
    broken = []
    for source, target in relative_links():
        if source != page:
            continue
        path, _, anchor = target.partition("#")
        resolved = (page.parent / path).resolve()
        if not resolved.exists():
            broken.append(f"{target} (no such file)")
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            broken.append(f"{target} (no heading with that anchor)")
    assert not broken, f"{page.relative_to(REPO)}: broken links: {broken}"


def test_every_docs_page_and_figure_is_linked():
    linked = {(source.parent / target.partition("#")[0]).resolve() for source, target in relative_links()}
    targets = sorted(DOCS.rglob("*.md")) + sorted(DOCS.rglob("*.png"))
    # a link to a folder shows its README.md (as GitHub renders it), nothing else in it
    orphans = [str(p.relative_to(REPO)) for p in targets
               if p.resolve() not in linked and not (p.name == "README.md" and p.parent.resolve() in linked)]
    assert not orphans, f"linked from nowhere (README.md or a docs page should link them): {orphans}"
