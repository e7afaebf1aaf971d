"""The command lines the README and every page under docs/ show, read as a shell reads them: the ``python``,
``umrl`` and ``make`` commands of their bash blocks and inline code spans, comments cut, continuations and
multi-line quotes joined, ``cmd1; cmd2``, ``&&``, ``&`` and ``for ... do`` split into their commands, a synopsis's
``a|b`` choices and ``recipes/*.py`` globs spelled out (one command each), and shell
variables replaced by the value the page gives them (``R=...`` on a line of the block, in a comment or in an inline
code span, the first value of ``for s in 0 1 2``), or by the value of a documented call (:data:`TEMPLATE_VALUES`, for the parameters of
the shell helpers a page defines)."""
from __future__ import annotations

import re
import shlex
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PAGES = ["README.md", *sorted(str(p.relative_to(REPO)) for p in (REPO / "docs").rglob("*.md"))]
PROGRAMS = ("python", "umrl", "make")

TEMPLATE_VALUES = {
    # plan.md's helpers, as its first table row calls them: `maml point_nav diayn 0 100 20 results/point_nav/diayn_ref
    # trpo.hvp=analytic`, `diayn point_nav 0 50000 50000`, `export_skills SOURCE DESTINATION`
    "docs/results/plan.md": {
        "$(resume": "true", "env": "point_nav", "p": "diayn", "s": "0", "n": "100", "every": "20",
        "keep": "true", "d": "results/point_nav/uml_diayn_ref/seed0", "@": "trpo.hvp=analytic",
        "extra": "diayn_checkpoint=results/point_nav/diayn_ref/seed0", "1": "point_nav", "2": "0", "3": "50000",
        "4": "50000",
    },
    # the loop of the measured runs (`for s in 0 1 2; do R=...`): its first seed, a fresh start
    "docs/measurements/2026-11-26-h100/README.md": {"s": "0", "R": "false"},
    "docs/measurements/2026-11-26-h200/README.md": {"s": "0"},
    "docs/results/claims.md": {"s": "0"},  # the paper-budget DIAYN runs of seeds 0, 1 and 2
}
"""Per page, values of the shell variables its commands use without setting them (a helper's parameters)."""


@dataclass(frozen=True)
class DocCommand:
    """One command a page shows: ``page``, ``text`` (as shown, continuations joined) and ``argv`` (the program and
    its arguments after variable substitution, as the shell passes them: quotes removed)."""

    page: str
    text: str
    argv: tuple[str, ...]

    def __str__(self) -> str:
        return f"{self.page}: {self.text}"


def _snippets(text: str) -> list[str]:
    """The bash blocks (fenced ``bash`` or unlabelled) and the inline code spans of a page."""
    blocks = re.findall(r"^```(?:bash|sh|)\n(.*?)^```", text, flags=re.DOTALL | re.MULTILINE)
    prose = re.sub(r"^```.*?^```", "", text, flags=re.DOTALL | re.MULTILINE)
    # a span may wrap onto the next line of its paragraph; `\|` is a | inside a table
    spans = [" ".join(span.replace("\\|", "|").split()) for span in re.findall(r"`([^`]+)`", prose)]
    return blocks + [span for span in spans if " " in span and span.split(" ", 1)[0] in (*PROGRAMS, "for")]


def spell_out(text: str, pattern: str, separator: str) -> list[str]:
    """Every spelling of ``text`` with each match of ``pattern`` replaced by one of its choices (the match's last
    group, or the whole match, split at ``separator``): every combination."""
    match = re.search(pattern, text)
    if not match:
        return [text]
    return [variant for choice in match.group(match.lastindex or 0).split(separator)
            for variant in spell_out(text[:match.start()] + choice + text[match.end():], pattern, separator)]


SYNOPSIS_CHOICES = r"[\w.-]+(?:\|[\w.-]+)+"
"""A synopsis's ``a|b|c`` (no spaces: not a pipe)."""


def _logical_lines(snippet: str) -> list[str]:
    """Lines with ``\\`` continuations joined, comments cut and a quote left open joined to the next line."""
    lines, pending = [], ""
    for line in snippet.replace("\\\n", " ").splitlines():
        pending = f"{pending}\n{line}" if pending else line
        try:
            shlex.split(pending, comments=False)
        except ValueError:  # an open quote (python -c "...): the command goes on
            continue
        lines.append(re.split(r"(?:^|\s)#(?:\s|$)", pending, maxsplit=1)[0].strip())
        pending = ""
    return [line for line in lines if line]


def _variables(snippet: str, page_values: dict[str, str]) -> dict[str, str]:
    values = dict(page_values)
    values.update({name: first for name, first in re.findall(r"\bfor (\w+) in (\S+?);?\s", snippet + " ")})
    values.update(dict(re.findall(r"(?:^|#\s*|;\s*)([A-Z]\w*)=([^\s;]+)", snippet, flags=re.MULTILINE)))
    return values


def _substitute(line: str, values: dict[str, str]) -> str:
    for call in (key for key in values if key.startswith("$(")):  # a helper's output: `$(resume DIR)`
        line = re.sub(re.escape(call) + r"[^)]*\)", values[call], line)

    def value(match: re.Match) -> str:
        name = match.group(1) or match.group(2)
        if name not in values:
            raise KeyError(f"${name} has no value on the page (nor in TEMPLATE_VALUES): {line}")
        return values[name]

    line = re.sub(r"\$\{(\w+)\}|\$(\w+|@)", value, line)
    # a placeholder of several words (`<the 200 k DIAYN run>`) is one word of the command
    return re.sub(r"<([A-Za-z][^<>\n]*)>", lambda m: "<" + "_".join(m.group(1).split()) + ">", line)


def _commands(line: str) -> list[list[str]]:
    """The simple commands of a shell line, each as its words (``VAR=value`` prefixes and ``do`` dropped)."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars=";&|()")
    lexer.whitespace_split = True
    lexer.commenters = ""
    commands, words = [], []
    for token in [*lexer, ";"]:
        if token and set(token) <= set(";&|()"):
            commands.append(words)
            words = []
        else:
            words.append(token)
    out = []
    for words in commands:
        while words and (words[0] in ("do", "then") or re.fullmatch(r"[A-Za-z_]\w*=\S*", words[0])):
            words = words[1:]
        if words[:1] == ["python"] and len(words) > 1 and "*" in words[1]:  # `python recipes/*.py`: each file
            out += [["python", str(path.relative_to(REPO)), *words[2:]] for path in sorted(REPO.glob(words[1]))]
        elif words and words[0] in PROGRAMS:
            out.append(words)
    return out


def doc_commands() -> list[DocCommand]:
    """Every ``python``, ``umrl`` and ``make`` command of :data:`PAGES`, in page order."""
    found = []
    for page in PAGES:
        text = (REPO / page).read_text()
        page_values = {**TEMPLATE_VALUES.get(page, {}), **dict(re.findall(r"`([A-Z]\w*)=([^\s`]+)`", text))}
        for snippet in _snippets(text):
            values = _variables(snippet, page_values)
            for line in _logical_lines(snippet):
                if not re.search(rf"(?:^|[\s;&(])(?:{'|'.join(PROGRAMS)})\s", line + " "):
                    continue
                for variant in spell_out(_substitute(line, values), SYNOPSIS_CHOICES, "|"):
                    found += [DocCommand(page, line, tuple(words)) for words in _commands(variant)]
    return found
