"""The documentation describes today's code (README.md and docs/*.md).

Three checks, each a small function tested on a deliberately bad text first,
so a check that could never fail is caught too:

* every dotted ``ftc.x.y`` name in a code span or code block imports (a
  module) or resolves (an attribute of one);
* every repository path the text mentions exists. Checked: paths under the
  repository's source roots (``CHECKED_ROOTS``), paths relative to the package
  (``control/run/runner.py`` is ``python/ftc/control/run/runner.py``) and the targets
  of Markdown links and images. Not checked, by rule: anything else, in
  particular ``build/...`` (made by scripts/setup.sh), ``runs/...`` (written
  by the tools), ``.venv/...`` and paths inside a run directory. Globs
  (``scenarios/*.toml``), braces (``replay_on_bus.{sh,md}``) and capital
  placeholders (``scenarios/NAME.toml``) must match at least one file;
* no development history: no "fourth round" / "8th round", "this session",
  commit hashes or "issue 11". History belongs in CHANGELOG.md.
"""

from __future__ import annotations

import importlib
import importlib.util
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "python" / "ftc"
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]

CHECKED_ROOTS = ("python", "scripts", "tests", "docs", "scenarios", "cpp", "lcmtypes",
                 "examples", r"\.ci")
ROOMS = ("common", "plant", "learning", "control", "experiments", "tools")

# Sections the history check skips (names and paths in them are still checked).
HISTORY_EXEMPT_SECTIONS: dict[str, tuple[str, ...]] = {}


# ----------------------------------------------------------------------------
# the checking functions

_FENCE = re.compile(r"^```[^\n]*\n(.*?)^```", re.S | re.M)
_INLINE = re.compile(r"`([^`\n]+)`")
_DOTTED = re.compile(r"(?<![\w.])ftc(?:\.[A-Za-z_]\w*)+")


def code_spans(text: str) -> list[str]:
    """The contents of the fenced code blocks and inline code spans of Markdown text."""
    blocks = _FENCE.findall(text)
    rest = _FENCE.sub("", text)
    return blocks + _INLINE.findall(rest)


_ROOM_DOTTED = re.compile(r"(?<![\w.])(?:%s)\.[a-z_]\w*(?:\.[A-Za-z_]\w*)*" % "|".join(ROOMS))


def dotted_names(text: str) -> set[str]:
    """Every ``ftc.a.b`` name in the text's code spans and blocks, and every
    package-relative one (``learning.ppo.UpdateStats`` is
    ``ftc.learning.ppo.UpdateStats``) in its inline spans whose second part is
    a module of that room (so ``plant.step(valves)``, a variable, is not one)."""
    names = {m for span in code_spans(text) for m in _DOTTED.findall(span)}
    for span in _INLINE.findall(_FENCE.sub("", text)):
        for m in _ROOM_DOTTED.findall(span):
            room, module = m.split(".")[:2]
            if (PACKAGE / room / f"{module}.py").is_file():
                names.add(f"ftc.{m}")
    return names


def resolve(name: str) -> str | None:
    """None if ``name`` is an importable module or an attribute of one, else why not."""
    parts = name.split(".")
    for i in range(len(parts), 0, -1):
        module_name = ".".join(parts[:i])
        try:
            obj = importlib.import_module(module_name)
        except ModuleNotFoundError as e:
            if e.name and (module_name == e.name or module_name.startswith(e.name + ".")):
                continue  # this prefix is no module; try a shorter one
            return f"{name}: importing {module_name} fails: {e}"
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                return (f"{name}: no module {'.'.join(parts[:i + 1])}, and "
                        f"{'.'.join(parts[:i])} has no attribute {attr!r}")
            obj = getattr(obj, attr)
            i += 1
        return None
    return f"{name}: no such module"


_ROOT_PATH = re.compile(r"(?<![\w./~-])(?:%s)/(?:[\w.*-]|/|\{[\w.,-]+\})*"
                        % "|".join(CHECKED_ROOTS))
_ROOM_PATH = re.compile(r"(?<![\w./~-])(?:ftc/|(?:%s)/)(?:[\w-]+/)*[\w-]+\.py\b" % "|".join(ROOMS))
_LINK = re.compile(r"\]\(([^)\s]+)\)")
_PLACEHOLDER = re.compile(r"\b[A-Z][A-Z_]{2,}\b")


def _expand_braces(path: str) -> list[str]:
    m = re.search(r"\{([^}]*)\}", path)
    if not m:
        return [path]
    return [p for alt in m.group(1).split(",")
            for p in _expand_braces(path[:m.start()] + alt + path[m.end():])]


def path_exists(path: str, base: Path) -> bool:
    """Whether the path (glob, braces and capital placeholders allowed) names at
    least one file or directory under base."""
    for alt in _expand_braces(path.rstrip("/")):
        pattern = _PLACEHOLDER.sub("*", alt)
        if any(c in pattern for c in "*?["):
            if not any(base.glob(pattern)):
                return False
        elif not (base / pattern).exists():
            return False
    return True


def missing_paths(text: str, doc_dir: Path, repo: Path = REPO) -> list[str]:
    """The paths the text mentions that do not exist (see the module docstring)."""
    missing = []
    for m in _ROOT_PATH.finditer(text):
        path = m.group(0).rstrip(".")
        if path.count("/") >= 1 and path.split("/", 1)[1] and not path_exists(path, repo):
            missing.append(path)
    for m in _ROOM_PATH.finditer(text):
        path = m.group(0)
        if not path_exists(path.removeprefix("ftc/"), repo / "python" / "ftc"):
            missing.append(path)
    for m in _LINK.finditer(text):
        target = m.group(1).split("#", 1)[0]
        if target and not re.match(r"[a-z]+:", target) and not path_exists(target, doc_dir):
            missing.append(target)
    return missing


_ORDINALS = ("first|second|third|fourth|fifth|sixth|seventh|eighth|ninth|tenth|"
             "eleventh|twelfth|\\d+(?:st|nd|rd|th)")
_HEX = r"\b[0-9a-f]{7,40}\b"
HISTORY_PATTERNS = {
    "a development round": re.compile(rf"\b(?:{_ORDINALS})[\s-]+rounds?\b"
                                      r"|\b(?:this|that|last|next|previous) round\b", re.I),
    "this session": re.compile(r"\bthis session\b", re.I),
    # a hash after a word that introduces one, or a token that looks like an
    # abbreviated hash by itself (hex digits and letters mixed; a run of
    # digits alone is a number, of letters alone a word)
    "a commit hash": re.compile(
        rf"\b(?:commits?|revisions?|rev|sha|hash|code of)\b[^\n.;]{{0,40}}?{_HEX}"
        r"|\b(?=[0-9a-f]*[a-f])(?=[0-9a-f]*[0-9])[0-9a-f]{7,40}\b", re.I),
    "an issue number": re.compile(r"\bissues?\s+#?\d+|(?<![\w&])#\d+\b", re.I),
    # the design notes outside the repository, which a reader cannot open
    "an outside note": re.compile(r"\bcontroller-notes\b", re.I),
}


def _drop_sections(text: str, headings: tuple[str, ...]) -> str:
    """The text without the sections that start with these headings (each up to
    the next heading of the same or a higher level)."""
    for heading in headings:
        level = len(heading) - len(heading.lstrip("#"))
        start = text.find(heading)
        if start < 0:
            continue
        nxt = re.compile(r"^#{1,%d} " % level, re.M).search(text, start + len(heading))
        text = text[:start] + (text[nxt.start():] if nxt else "")
    return text


def history(text: str) -> list[str]:
    """Each mention of development history in the text, as 'what: line'."""
    found = []
    for what, pattern in HISTORY_PATTERNS.items():
        for m in pattern.finditer(text):
            line = text[text.rfind("\n", 0, m.start()) + 1:text.find("\n", m.end())]
            found.append(f"{what}: {m.group(0)!r} in {line.strip()[:160]!r}")
    return found


# ----------------------------------------------------------------------------
# the checks can fail

def test_dotted_names_are_taken_from_code_only():
    text = ("Prose ftc.not_code.\n`ftc.plant.launch` and\n```python\nimport ftc.ppo\n"
            "plant.reset()\n```\n`learning.ppo.UpdateStats`, `plant.step(valves)`\n")
    assert dotted_names(text) == {"ftc.plant.launch", "ftc.ppo", "ftc.learning.ppo.UpdateStats"}


@pytest.mark.parametrize("name", ["ftc.ppo", "ftc.world_model", "ftc.env.FuelTransferEnv",
                                  "ftc.plant.no_such_function", "ftc.experiments.methods.NOPE"])
def test_a_name_that_does_not_exist_is_reported(name):
    assert resolve(name) is not None


@pytest.mark.parametrize("name", ["ftc.plant", "ftc.plant.launch", "ftc.learning.ppo.PPOConfig",
                                  "ftc.experiments.methods.METHODS", "ftc.controller"])
def test_a_name_that_exists_resolves(name):
    assert resolve(name) is None


def test_a_missing_path_is_reported_and_outputs_are_not_checked(tmp_path):
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "a.md").write_text("")
    (tmp_path / "scenarios").mkdir()
    (tmp_path / "scenarios" / "single.toml").write_text("")
    text = ("See docs/a.md, docs/gone.md and `python/ftc/experiments.py`; "
            "scenarios/*.toml, scenarios/NAME.toml and docs/{a,b}.md; "
            "build/plant and runs/x/report.md are outputs. ![f](figures/f.png) [ok](a.md)")
    assert missing_paths(text, tmp_path / "docs", repo=tmp_path) == [
        "docs/gone.md", "python/ftc/experiments.py", "docs/{a,b}.md", "figures/f.png"]


def test_a_package_relative_path_is_checked_under_python_ftc():
    assert missing_paths("`control/run/runner.py` and learning/no_such.py", REPO / "docs") == [
        "learning/no_such.py"]


@pytest.mark.parametrize("text", [
    "measured in the fourth round", "the 8th round's machine", "as of this session",
    "commit a6258c1", "controller revisions 4d49004 and f6a323f", "at e2e5c21, idle",
    "the code of commit 1234567", "see issue 11", "fixes #12", "measured this round"])
def test_history_is_found(text):
    assert history(text), text


@pytest.mark.parametrize("text", [
    "8 x `--rounds` blocks", "a third DAgger round", "`--rounds 3`", "avx512-amd",
    "sha256 of its .dsc", "0.0036/0.9991", "2.4e-07", "the issue's tracker", "1e-5",
    "round by round", "round(e.value, 3)"])
def test_ordinary_text_is_not_history(text):
    assert not history(text), text


def test_an_exempt_section_ends_at_the_next_heading_of_its_level():
    text = "# T\n## A\nfourth round\n### A.1\nfifth round\n## B\nsixth round\n"
    assert _drop_sections(text, ("## A",)) == "# T\n## B\nsixth round\n"


# ----------------------------------------------------------------------------
# the documentation

def _rel(doc: Path) -> str:
    return doc.relative_to(REPO).as_posix()


@pytest.mark.parametrize("doc", DOCS, ids=_rel)
def test_every_ftc_name_in_the_docs_exists(doc):
    errors = [e for name in sorted(dotted_names(doc.read_text())) if (e := resolve(name))]
    assert not errors, "\n".join(errors)


@pytest.mark.parametrize("doc", DOCS, ids=_rel)
def test_every_repository_path_in_the_docs_exists(doc):
    missing = missing_paths(doc.read_text(), doc.parent)
    assert not missing, "no such path: " + ", ".join(missing)


@pytest.mark.parametrize("doc", DOCS, ids=_rel)
def test_the_docs_carry_no_development_history(doc):
    text = _drop_sections(doc.read_text(), HISTORY_EXEMPT_SECTIONS.get(_rel(doc), ()))
    found = history(text)
    assert not found, "history belongs in CHANGELOG.md:\n" + "\n".join(found)


# ----------------------------------------------------------------------------
# result tables come from files

def _render_module():
    spec = importlib.util.spec_from_file_location("render_results",
                                                  REPO / "scripts" / "render_results.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_table_that_disagrees_with_its_file_is_rendered_anew():
    render = _render_module()
    name = "quality_single"  # a table of the default kind (per-interval means)
    good = render.rendered(f"x\n<!-- results: {name} -->\nstale\n<!-- /results -->\ny\n")
    assert "stale" not in good and good.startswith("x\n") and good.endswith("y\n")
    assert render.rendered(good) == good  # rendering is idempotent
    tampered = good.replace("|", "| 9.999 |", 1)
    assert render.rendered(tampered) != tampered
    with pytest.raises(SystemExit):
        render.rendered("<!-- results: no-such-table -->\n<!-- /results -->")


def test_every_result_table_in_the_docs_equals_its_file():
    render = _render_module()
    blocks = [m.group(2) for doc in DOCS for m in render.BLOCK.finditer(doc.read_text())]
    assert blocks, "no rendered result tables in the docs"
    assert render.main(["--check"]) == 0


# tables typed into the docs that hold specifications, not measurements (header rows)
SPEC_TABLES = {
    "| figure | group | what it measures | aim |",  # docs/benchmarks.md: the aims
    "| exit | cause | example |",  # docs/controller.md: exit codes (an option's default)
    "| test | what it shows |",  # docs/ecosystem.md: a test's own thresholds
    "| symbol | meaning | nominal |",  # docs/plant-model.md: nominal parameters
}
DECIMAL = re.compile(r"(?<![\w.])\d+\.\d+")


def typed_tables(text: str) -> list[tuple[int, list[str]]]:
    """The Markdown tables of ``text`` outside rendered result blocks: (first
    line number, lines)."""
    tables, start, inside = [], None, False
    lines = text.split("\n")
    for i, line in enumerate([*lines, ""]):
        inside = (inside or line.startswith("<!-- results:")) and \
            not line.startswith("<!-- /results")
        if line.startswith("|") and not inside:
            start = i if start is None else start
        elif start is not None:
            tables.append((start + 1, lines[start:i]))
            start = None
    return tables


def measured_tables(text: str) -> list[tuple[int, str]]:
    """Typed tables that hold decimal figures and are not specification tables."""
    return [(n, rows[0]) for n, rows in typed_tables(text)
            if rows[0].strip() not in SPEC_TABLES and DECIMAL.search("\n".join(rows[2:]))]


def test_a_typed_table_of_figures_is_found_and_a_rendered_one_is_not():
    typed = "text\n\n| method | mean |\n|---|---|\n| a | 0.91 |\n\nmore\n"
    rendered = "<!-- results: x -->\n| method | mean |\n|---|---|\n| a | 0.91 |\n<!-- /results -->\n"
    spec = "| exit | cause | example |\n|---|---|---|\n| 3 | after 0.05 s | x |\n"
    assert measured_tables(typed) == [(3, "| method | mean |")]
    assert measured_tables(rendered) == [] and measured_tables(spec) == []
    assert measured_tables("| a | b |\n|---|---|\n| x | 3 |\n") == []  # no decimal figure


@pytest.mark.parametrize("doc", DOCS, ids=_rel)
def test_tables_of_measured_figures_are_rendered_from_result_files(doc):
    found = measured_tables(doc.read_text())
    assert not found, (f"{_rel(doc)}: tables of figures typed by hand (render them from "
                       f"docs/results/ with scripts/render_results.py): {found}")
