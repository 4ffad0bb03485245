"""The code a result depends on, derived rather than listed: the static import
closure of some ``ftc`` modules (every ``ftc`` module their source files
import, read with ``ast``, never executed), hashed with its texts.

A cache keyed by it is invalidated by an edit to any module the cached
computation can run, and by no other edit. Imports inside functions count
(the closure over-approximates what runs, never under-approximates it)."""

from __future__ import annotations

import ast
import hashlib
from pathlib import Path

from ftc.common.paths import PACKAGE_DIR, REPO_ROOT

NATIVE = "cpp/plant"  # the plant's C++ sources, relative to a checkout
# the native core's (ftc._core: the physics and its bindings), under NATIVE; the
# same list is in cpp/cmake/native_sources.cmake (the install's digest). The
# plant's LCM node and its tools are not in it: no computation in process runs them.
NATIVE_DIRS = ("bindings", "core")
INSTALLED_NATIVE_DIGEST = "native_sources.sha256"  # what an install writes into the package


def module_file(module: str, package_dir: Path = PACKAGE_DIR) -> Path | None:
    """The source of ``ftc.x.y`` under ``package_dir`` (the ``ftc`` directory), or None."""
    parts = module.split(".")[1:]
    base = package_dir.joinpath(*parts)
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


def _imports(path: Path, module: str) -> set[str]:
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")
                anchor = anchor[:len(anchor) - node.level + 1]
                base = ".".join([*anchor, base] if base else anchor)
            out.add(base)
            out.update(f"{base}.{a.name}" for a in node.names)  # a submodule imported by name
    return {m for m in out if m == "ftc" or m.startswith("ftc.")}


def import_closure(modules: list[str], package_dir: Path = PACKAGE_DIR) -> dict[str, Path]:
    """module -> source file of ``modules``, their packages and every ``ftc``
    module they import, transitively (names that are not source files, such as
    the built ``ftc._core`` or a function imported by name, are left out)."""
    found: dict[str, Path] = {}
    todo = list(modules)
    while todo:
        module = todo.pop()
        if module in found:
            continue
        path = module_file(module, package_dir)
        if path is None:
            continue
        found[module] = path
        parts = module.split(".")
        todo.extend(".".join(parts[:i]) for i in range(1, len(parts)))  # its packages
        todo.extend(_imports(path, module))
    return dict(sorted(found.items()))


def closure_digest(modules: list[str], package_dir: Path = PACKAGE_DIR) -> str:
    """SHA-256 (hex) of the import closure's module names and texts."""
    h = hashlib.sha256()
    for name, path in import_closure(modules, package_dir).items():
        h.update(name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def native_source_digest(root: Path | None = None) -> str | None:
    """SHA-256 over every file under ``root/cpp/plant``'s :data:`NATIVE_DIRS` (the
    checkout's by default): "relative/path sha256\\n" per file (relative to
    cpp/plant), sorted by path; in an installed package, the digest its install
    wrote (``ftc/native_sources.sha256``); None if neither."""
    base = (REPO_ROOT if root is None else Path(root)) / NATIVE
    if base.is_dir():
        files = [p for d in NATIVE_DIRS for p in (base / d).rglob("*") if p.is_file()]
        lines = "".join(f"{p.relative_to(base).as_posix()} "
                        f"{hashlib.sha256(p.read_bytes()).hexdigest()}\n"
                        for p in sorted(files, key=lambda q: q.relative_to(base).as_posix()))
        return hashlib.sha256(lines.encode()).hexdigest()
    installed = PACKAGE_DIR / INSTALLED_NATIVE_DIGEST
    return installed.read_text().strip() if root is None and installed.is_file() else None
