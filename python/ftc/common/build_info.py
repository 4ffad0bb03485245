"""Locations of build products, with clear errors when the build is missing."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

from ftc import BUILD_DIR, REPO_ROOT


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


def plant_binary() -> Path:
    """Path of the plant executable (``FTC_PLANT_BIN`` overrides ``build/plant``)."""
    path = Path(os.environ.get("FTC_PLANT_BIN", BUILD_DIR / "plant"))
    if not path.is_file():
        raise BuildMissingError(f"plant executable not found at {path}; run scripts/setup.sh")
    return path


def echo_binary() -> Path:
    """Path of the LCM echo responder used as the benchmark floor."""
    path = BUILD_DIR / "lcm_echo"
    if not path.is_file():
        raise BuildMissingError(f"lcm_echo not found at {path}; run scripts/setup.sh")
    return path


def policy_node_binary() -> Path:
    """build/policy_node: the embedded controller (cpp/policy/policy_node.cpp)."""
    path = BUILD_DIR / "policy_node"
    if not path.is_file():
        raise BuildMissingError(f"policy_node not found at {path}; run scripts/setup.sh")
    return path


def recorder_binary() -> Path:
    """build/lcm_recorder: records a run's traffic in lcm-logger's file format
    without lcm-logger's 30-message subscription queue, which dropped plant
    states whenever the recorder was briefly descheduled (measured: 2 to 752
    of ~5,000 per run on a loaded 2-core machine). See cpp/plant/apps/recorder.cpp."""
    path = BUILD_DIR / "lcm_recorder"
    if not path.is_file():
        raise BuildMissingError(f"lcm_recorder not found at {path}; run scripts/setup.sh")
    return path


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
