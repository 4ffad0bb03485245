"""Locations of build products, with clear errors when the build is missing."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

from ftc.common.paths import BUILD_DIR, PACKAGE_DIR, REPO_ROOT


class BuildMissingError(RuntimeError):
    """The C++ build (plant binary, bindings or generated types) is not there."""


def ftc_version() -> str:
    """The package's version: the one place it lives is pyproject.toml (read from
    the installed metadata, or from the checkout's pyproject.toml)."""
    pyproject = REPO_ROOT / "pyproject.toml"
    if pyproject.is_file():
        import tomllib

        return str(tomllib.loads(pyproject.read_text())["project"]["version"])
    from importlib import metadata

    return metadata.version("ftc")


def _program(name: str, what: str) -> Path:
    """A C++ program of the project: a checkout's build/NAME, else the one
    installed with the package (ftc/bin/NAME)."""
    for path in (BUILD_DIR / name, PACKAGE_DIR / "bin" / name):
        if path.is_file():
            return path
    raise BuildMissingError(f"{what} not found at {BUILD_DIR / name} (a checkout: run "
                            f"scripts/setup.sh) or {PACKAGE_DIR / 'bin' / name} (installed: "
                            "pip install the project)")


def plant_binary() -> Path:
    """Path of the plant executable (``FTC_PLANT_BIN`` overrides where it is looked for)."""
    if "FTC_PLANT_BIN" in os.environ:
        path = Path(os.environ["FTC_PLANT_BIN"])
        if not path.is_file():
            raise BuildMissingError(f"plant executable not found at {path} (FTC_PLANT_BIN)")
        return path
    return _program("plant", "plant executable")


def echo_binary() -> Path:
    """Path of the LCM echo responder used as the benchmark floor."""
    return _program("lcm_echo", "lcm_echo")


def policy_node_binary() -> Path:
    """build/policy_node: the embedded controller (cpp/policy/policy_node.cpp)."""
    return _program("policy_node", "policy_node")


def recorder_binary() -> Path:
    """build/lcm_recorder: records a run's traffic in lcm-logger's file format
    without lcm-logger's 30-message subscription queue, which dropped plant
    states whenever the recorder was briefly descheduled (measured: 2 to 752
    of ~5,000 per run on a loaded 2-core machine). See cpp/plant/apps/recorder.cpp."""
    return _program("lcm_recorder", "lcm_recorder")


def git_revision() -> str:
    """The repository's HEAD commit (with '-dirty' if the tree has changes), or 'unknown'."""
    try:
        rev = subprocess.run(["git", "-C", str(REPO_ROOT), "rev-parse", "HEAD"],
                             capture_output=True, text=True, check=True).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(REPO_ROOT), "status", "--porcelain", "-uno"],
                               capture_output=True, text=True, check=True).stdout.strip()
        return rev + ("-dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"
