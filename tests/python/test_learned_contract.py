"""The controllers that learn the plant use no plant equations, and the checks
that say so would notice if they did (issue: controllers that learn the plant).

* import-linter's contract "the learned-plant controllers use no plant
  equations" (pyproject.toml): the learned modules, and everything they
  import, never reach the identification, the evaluators and environments on
  the C++ physics, or the experiments' scenarios;
* the native module ``ftc._core`` is built, not a source file, so it is not in
  import-linter's graph: :func:`native_core_importers` finds every module the
  learned ones import that imports it; only the plant link (it runs the
  plant itself with ``--link core``) and the policy's pretraining (it hashes
  the native file into its cache key) may.

Each check is also run on a copy of the package with one forbidden import
added, and must fail there.
"""

from __future__ import annotations

import ast
import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import grimp
import pytest

REPO = Path(__file__).resolve().parents[2]
CONTRACT = "the learned-plant controllers use no plant equations"
# a room and a module: every module in ftc.control.agents.learned, present or added later
LEARNED = ("ftc.control.agents.learned", "ftc.learning.feature_model",
           "ftc.learning.history_policy")
# the plant link runs the plant itself (not a model of it); pretraining hashes the
# native file into its cache key (the nominal plants it pretrains on change with it)
ALLOWED_NATIVE = {"ftc.plant.link", "ftc.learning.pretrain"}


def native_core_importers(package_dir: Path, sources: tuple[str, ...]) -> set[str]:
    """The modules among ``sources`` and everything they import (in the package
    under ``package_dir``, i.e. ``.../python``) that import ``ftc._core``."""
    code = (f"import sys; sys.path.insert(0, {str(package_dir)!r}); import grimp, json; "
            f"g = grimp.build_graph('ftc'); "
            f"s = set({list(sources)!r}).union(*[g.find_descendants(m) for m in {list(sources)!r}]); "
            f"print(json.dumps(sorted(s.union(*[g.find_upstream_modules(m) for m in s]))))")
    # a fresh interpreter: the package copy must not mix with the one imported here
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, timeout=120).stdout
    import json

    found = set()
    for module in json.loads(out):
        path = _source(package_dir, module)
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module == "ftc" and \
                    any(a.name == "_core" for a in node.names):
                found.add(module)
            elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("ftc._core"):
                found.add(module)
            elif isinstance(node, ast.Import) and \
                    any(a.name.startswith("ftc._core") for a in node.names):
                found.add(module)
    return found


def _source(package_dir: Path, module: str) -> Path:
    base = package_dir.joinpath(*module.split("."))
    return base / "__init__.py" if base.is_dir() else base.with_suffix(".py")


def _lint(cwd: Path, python_dir: Path) -> subprocess.CompletedProcess:
    exe = Path(sys.executable).with_name("lint-imports")
    env = {"PATH": "/usr/bin:/bin", "PYTHONPATH": str(python_dir)}
    return subprocess.run([str(exe) if exe.exists() else "lint-imports",
                           "--contract", _contract_id(cwd), "--no-cache"], cwd=cwd, capture_output=True,
                          text=True, timeout=300, env=env)


def _contract_id(cwd: Path) -> str:
    import tomllib

    contracts = tomllib.loads((cwd / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    for c in contracts:
        if c["name"] == CONTRACT:
            return c.get("id", "")
    raise AssertionError(f"no contract named {CONTRACT!r} in pyproject.toml")


@pytest.fixture()
def package_copy(tmp_path: Path) -> Path:
    """A copy of the repository's Python sources and pyproject.toml under tmp_path."""
    shutil.copytree(REPO / "python" / "ftc", tmp_path / "python" / "ftc",
                    ignore=shutil.ignore_patterns("__pycache__"))
    shutil.copy(REPO / "pyproject.toml", tmp_path / "pyproject.toml")
    return tmp_path


def test_the_learned_modules_exist_and_are_the_contracts_sources():
    import tomllib

    contracts = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["importlinter"]["contracts"]
    contract = next(c for c in contracts if c["name"] == CONTRACT)
    assert set(contract["source_modules"]) == set(LEARNED)
    for module in LEARNED:
        assert importlib.util.find_spec(module) is not None, module
    assert {"ftc.learning.identify", "ftc.control.planning.physics", "ftc.control.agents.physics"} <= \
        set(contract["forbidden_modules"])


def test_only_the_plant_link_imports_the_native_core():
    assert native_core_importers(REPO / "python", LEARNED) <= ALLOWED_NATIVE


@pytest.mark.parametrize("line,where", [
    ("from ftc.learning.identify import Identifier", "learning/feature_model.py"),
    # a module added to the learned room is under the rule without being listed
    ("from ftc.control.planning.physics.evaluators import ParamsEvaluator",
     "control/agents/learned/new_agent.py"),
    # the adaptive policy's run-time modules: its agent may not reach its teacher, nor
    # its student's module the training (which runs the true physics)
    ("from ftc.control.planning.physics.teacher import PoolTeacher",
     "control/agents/learned/adaptive_policy.py"),
    ("from ftc.experiments.adaptive.dagger import train", "learning/history_policy.py"),
    # nor its online fine-tune rate settings on the true physics
    ("from ftc.control.planning.physics.evaluators import OracleEvaluator",
     "control/agents/learned/online_tune.py"),
])
def test_the_contract_fails_on_an_import_of_plant_equations(package_copy, line, where):
    kept = _lint(package_copy, package_copy / "python")
    assert kept.returncode == 0, kept.stdout[-2000:] + kept.stderr[-2000:]
    target = package_copy / "python" / "ftc" / where
    text = target.read_text() if target.exists() else '"""A new learned controller."""\n'
    target.write_text(text + f"\n{line}  # noqa\n")
    broken = _lint(package_copy, package_copy / "python")
    assert broken.returncode != 0
    assert f"{CONTRACT} BROKEN" in broken.stdout, broken.stdout[-3000:]


def test_the_native_core_check_fails_on_an_import_of_the_core(package_copy):
    python = package_copy / "python"
    assert native_core_importers(python, LEARNED) <= ALLOWED_NATIVE
    target = python / "ftc" / "control" / "agents" / "learned" / "learned_mpc.py"
    target.write_text(target.read_text() + "\n\ndef _physics():\n    from ftc import _core\n"
                      "    return _core.BatchRollout()\n")
    assert "ftc.control.agents.learned.learned_mpc" in native_core_importers(python, LEARNED)
