"""Where the package and its build products are: ``PACKAGE_DIR`` (this
package), ``REPO_ROOT`` (a checkout's root; meaningless when installed) and
``BUILD_DIR`` (``FTC_BUILD_DIR``, else ``<repo>/build``)."""

from __future__ import annotations

import os
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parents[1]
REPO_ROOT = PACKAGE_DIR.parents[1]
BUILD_DIR = Path(os.environ.get("FTC_BUILD_DIR", REPO_ROOT / "build")).resolve()

# The scenario files: a checkout's scenarios/, else the copy installed with the package.
SCENARIO_DIR = next((d for d in (REPO_ROOT / "scenarios", PACKAGE_DIR / "scenarios")
                     if d.is_dir()), PACKAGE_DIR / "scenarios")


def scenario_names() -> list[str]:
    """The names of the packaged scenarios ("abrupt", "multiple", "nominal", "single")."""
    return sorted(p.stem for p in SCENARIO_DIR.glob("*.toml"))


def scenario_file(scenario: str) -> str:
    """The scenario file a command line's ``scenario`` means: a name without a
    directory or suffix ("single") is the packaged scenario of that name
    (:data:`SCENARIO_DIR`), anything else a path, returned as given ('' stays
    '': the nominal plant). ValueError, one line, for an unknown name."""
    if not scenario or os.sep in scenario or scenario.endswith(".toml") \
            or os.path.exists(scenario):
        return scenario
    path = SCENARIO_DIR / f"{scenario}.toml"
    if not path.is_file():
        raise ValueError(f"unknown scenario name {scenario!r} (not a file, nor a scenario in "
                         f"{SCENARIO_DIR}; known: {', '.join(scenario_names())})")
    return str(path)
