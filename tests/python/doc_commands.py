"""The commands of the documentation, as the tests run them.

Every fenced ``bash`` and ``python`` block of README.md and docs/*.md is
preceded by a mark saying how it is kept honest:

    <!-- commands: run -->            tests/python/test_doc_commands.py runs each
                                      command in the checkout, as written
    <!-- commands: install -->        tests/python/test_install.py runs each one
                                      outside the checkout, beside a fresh venv
                                      ``myenv`` that has the package installed
    <!-- commands: illustration; tested by tests/python/FILE.py::TEST -->
                                      not run as written (too long for the test
                                      tiers, or it needs a second terminal); the
                                      named test runs a shorter equivalent

A command is a line of a ``bash`` block, with ``\\``-continued lines joined
(comment lines and blank lines are none), or a whole ``python`` block, run
as ``.venv/bin/python -`` with the block on its standard input.
"""

from __future__ import annotations

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
KINDS = ("run", "install", "illustration")

_BLOCK = re.compile(r"(?:^<!-- commands: (?P<mark>[^>]*?) -->\n)?^```(?P<lang>bash|python)\n"
                    r"(?P<body>.*?)^```", re.S | re.M)
_TESTED_BY = re.compile(r"^illustration; tested by (?P<test>tests/python/\S+\.py::\w+)$")


def blocks(text: str) -> list[tuple[str | None, str]]:
    """(mark or None, body as bash) of every ``bash`` and ``python`` block of
    Markdown ``text`` (a python block as the command that runs it)."""
    return [(m.group("mark"), m.group("body") if m.group("lang") == "bash" else
             f".venv/bin/python - <<'PYTHON'\n{m.group('body')}PYTHON\n")
            for m in _BLOCK.finditer(text)]


def commands(body: str) -> list[str]:
    """The commands of a block: continued lines joined, comments and blanks
    dropped; a python block's (a here-document) is one."""
    if body.startswith(".venv/bin/python - <<'PYTHON'\n"):
        return [body]
    joined = re.sub(r"\s*\\\n\s*", " ", body)
    return [line.strip() for line in joined.splitlines()
            if line.strip() and not line.strip().startswith("#")]


def mark_problem(mark: str | None) -> str | None:
    """Why a block's mark is not one of the kinds (with the test an illustration names)."""
    if mark is None:
        return "no <!-- commands: ... --> mark before it"
    if mark in ("run", "install"):
        return None
    m = _TESTED_BY.match(mark)
    if not m:
        return f"mark {mark!r} is not run, install or 'illustration; tested by FILE::TEST'"
    path, name = m.group("test").split("::")
    if not (REPO / path).is_file() or f"def {name}(" not in (REPO / path).read_text():
        return f"mark {mark!r}: no test {name} in {path}"
    return None


def marked(kind: str, docs: list[Path] = DOCS) -> list[tuple[Path, str]]:
    """(document, command) of every command under a ``kind`` mark in ``docs``."""
    return [(doc, c) for doc in docs for mark, body in blocks(doc.read_text())
            if mark == kind for c in commands(body)]
