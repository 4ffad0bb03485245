"""The Python modules a run can execute, read from the code: the static import
closure of its entry modules within the ``ftc`` package.

Every ``import`` and ``from ... import`` statement of a module counts, at any
depth (an import inside a function too: a run may take that path), relative
ones resolved; ``from P import name`` counts ``P.name`` when it is a module of
the package; importing ``a.b.c`` runs ``a``'s and ``a.b``'s ``__init__`` too,
and ``python -m`` of a package runs its ``__main__``. Modules outside the
package (the standard library, numpy, torch) are not followed, and a module
without a source file here (the native ``_core``: its C++ sources are keyed
apart) is left out, as are the message classes lcm-gen writes into an
installed package (generated from ``lcmtypes/``; absent from a checkout's
sources). A module named only in a string (the registry's ``"module:Class"``
agents) is an entry the caller names.

Used to key data by the code that made it (:mod:`ftc.experiments.reference_scores`):
a module outside the closure may change without staling it.
"""

from __future__ import annotations

import ast
from pathlib import Path
from typing import Iterable

PACKAGE = "ftc"
# lcm-gen's first line in every Python class it writes
_GENERATED = '"""LCM type definitions'


def module_file(name: str, package_dir: Path) -> Path | None:
    """The source file of module ``name`` (``ftc.x.y``) in ``package_dir`` (the
    ``ftc`` directory): ``x/y.py`` or ``x/y/__init__.py``; None if neither."""
    parts = name.split(".")
    if parts[0] != PACKAGE:
        return None
    base = package_dir.joinpath(*parts[1:])
    for path in (base.with_suffix(".py") if len(parts) > 1 else None, base / "__init__.py"):
        if path is not None and path.is_file():
            return path
    return None


def _with_parents(name: str) -> list[str]:
    parts = name.split(".")
    return [".".join(parts[:k]) for k in range(1, len(parts) + 1)]


def imported(name: str, path: Path, package_dir: Path) -> set[str]:
    """The ``ftc`` modules module ``name`` (its source ``path``) imports, each
    with its parent packages."""
    tree = ast.parse(path.read_bytes(), filename=str(path))
    is_package = path.name == "__init__.py"
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                found.update(_with_parents(alias.name))
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                anchor = name.split(".")
                anchor = anchor[:len(anchor) - node.level + (1 if is_package else 0)]
                base = ".".join(anchor + ([node.module] if node.module else []))
            else:
                base = node.module or ""
            found.update(_with_parents(base))
            for alias in node.names:
                if module_file(f"{base}.{alias.name}", package_dir) is not None:
                    found.add(f"{base}.{alias.name}")
    return {m for m in found if m.split(".")[0] == PACKAGE}


def _generated(path: Path) -> bool:
    with open(path, "rb") as f:
        return f.read(len(_GENERATED)).decode(errors="replace") == _GENERATED


def closure(entries: Iterable[str], package_dir: Path) -> dict[str, Path]:
    """Module name -> source file of every ``ftc`` module the ``entries`` (module
    names, as ``python -m`` or an import takes them) execute, sorted by name.
    ValueError naming an entry without a source file."""
    todo: list[str] = []
    for entry in entries:
        if module_file(entry, package_dir) is None:
            raise ValueError(f"import closure: no source file for entry module {entry!r} "
                             f"in {package_dir}")
        todo += _with_parents(entry)
        if module_file(f"{entry}.__main__", package_dir) is not None:
            todo.append(f"{entry}.__main__")
    seen: dict[str, Path] = {}
    while todo:
        name = todo.pop()
        if name in seen:
            continue
        path = module_file(name, package_dir)
        if path is None or _generated(path):
            continue
        seen[name] = path
        todo += sorted(imported(name, path, package_dir) - set(seen))
    return dict(sorted(seen.items()))
