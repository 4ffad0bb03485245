"""The package's architecture holds (docs/architecture.md):

* the rooms import only from themselves and from rooms below them
  (common < plant < learning < control < experiments < tools), checked by
  import-linter's contract in pyproject.toml;
* imports of the package's own modules sit at the top of modules; only the
  native pieces (the generated LCM types, the ``_core`` and ``_learn``
  bindings) may be
  imported inside functions, where a missing build gives a clear error late;
* no two modules import each other, directly or through others (type-checking
  imports counted): the import graph has no circle;
* no module is over 500 lines and no class over 200.
"""

from __future__ import annotations

import ast
import shutil
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "python" / "ftc"
NATIVE = {"ftc._core", "ftc._learn", "ftc.plant_state_t", "ftc.valve_command_t", "ftc.plant_control_t",
          "ftc.policy_ack_t",
          "ftc.policy_t", "ftc.policy_v2_t"}
# Modules that pull in torch, imported inside the one function that needs them, so
# that a tool's --help, parsing and refusals do not pay torch's start-up (1.3 s of
# CPU a process; the test suite starts hundreds). grimp still sees these imports.
HEAVY = {"ftc.control.agents.sb3", "ftc.experiments.model_search", "ftc.learning.world_model"}
MAX_MODULE_LINES, MAX_CLASS_LINES = 500, 200


def _modules() -> list[Path]:
    return sorted(PACKAGE.rglob("*.py"))


def test_import_linter_contract_is_kept():
    exe = Path(sys.executable).with_name("lint-imports")
    assert exe.exists() or shutil.which("lint-imports"), "import-linter is not installed"
    proc = subprocess.run([str(exe) if exe.exists() else "lint-imports"], cwd=REPO,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-2000:]
    assert "0 broken" in proc.stdout


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The circles of a directed import graph (its strongly connected
    components of more than one module), each sorted (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return circles


def test_the_circle_finder_finds_circles_and_only_those():
    assert import_circles({"a": {"b"}, "b": {"c"}, "c": set()}) == []
    assert import_circles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert import_circles({"a": {"b"}, "b": {"a"}, "c": {"d"}, "d": {"c"}}) == [["a", "b"],
                                                                                ["c", "d"]]


def test_the_import_graph_has_no_circle():
    import grimp  # import-linter's graph builder: every import statement, TYPE_CHECKING too

    sys.path.insert(0, str(PACKAGE.parent))
    graph = grimp.build_graph("ftc", include_external_packages=False)
    edges = {m: graph.find_modules_directly_imported_by(m) for m in graph.modules}
    assert import_circles(edges) == []


def _local_ftc_imports(tree: ast.AST) -> list[tuple[int, str]]:
    found = []
    for fn in ast.walk(tree):
        if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        for node in ast.walk(fn):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("ftc"):
                names = ([f"{node.module}.{a.name}" for a in node.names] if node.module == "ftc"
                         else [node.module])
                found += [(node.lineno, n) for n in names if n not in NATIVE | HEAVY]
            elif isinstance(node, ast.Import):
                found += [(node.lineno, a.name) for a in node.names
                          if a.name.startswith("ftc") and a.name not in NATIVE | HEAVY]
    return found


def test_only_native_pieces_are_imported_inside_functions():
    offenders = [f"{path.relative_to(REPO)}:{line} {name}" for path in _modules()
                 for line, name in _local_ftc_imports(ast.parse(path.read_text()))]
    assert not offenders, "function-local imports of ftc modules:\n" + "\n".join(offenders)


def test_the_check_finds_a_local_import():
    tree = ast.parse("def f():\n    from ftc.control import runner\n    from ftc import _core\n")
    assert _local_ftc_imports(tree) == [(2, "ftc.control")]


def test_modules_and_classes_are_small():
    big = []
    for path in _modules():
        text = path.read_text()
        lines = text.count("\n")
        if lines > MAX_MODULE_LINES:
            big.append(f"{path.relative_to(REPO)}: {lines} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.ClassDef):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_CLASS_LINES:
                    big.append(f"{path.relative_to(REPO)}: class {node.name} {n} lines")
    assert not big, "\n".join(big)
