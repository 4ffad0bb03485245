"""The version lives in one place (pyproject.toml): ``python -m ftc --version``
prints it and every run's config.json records it; the build links ./plant at
the repository root, as the C++ developer's path runs it."""

from __future__ import annotations

import json
import subprocess
import sys
import tomllib
from pathlib import Path

from ftc import BUILD_DIR
from ftc.common.build_info import ftc_version

REPO = Path(__file__).resolve().parents[2]
VERSION = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]


def test_the_version_is_pyprojects_and_python_m_ftc_prints_it():
    assert ftc_version() == VERSION
    out = subprocess.run([sys.executable, "-m", "ftc", "--version"], capture_output=True,
                         text=True, timeout=60, cwd=REPO)
    assert out.returncode == 0 and out.stdout.strip() == f"ftc {VERSION}"
    listing = subprocess.run([sys.executable, "-m", "ftc"], capture_output=True, text=True,
                             timeout=60, cwd=REPO).stdout
    assert "python -m ftc.controller" in listing and "python -m ftc.mpc" in listing


def test_a_runs_config_records_the_version(tmp_path, scenarios):
    from ftc.tools.controller import main

    out = tmp_path / "closed"
    assert main(["--method", "closed", "--link", "core", "--intervals", "1",
                 "--steps-per-interval", "16", "--scenario", str(scenarios / "single.toml"),
                 "--out", str(out), "--quiet"]) == 0
    assert json.loads((out / "config.json").read_text())["ftc_version"] == VERSION


def test_the_build_links_plant_at_the_repository_root():
    link = REPO / "plant"
    if BUILD_DIR != (REPO / "build").resolve():
        return  # another build directory (FTC_BUILD_DIR): its own link is its business
    assert link.is_symlink() and link.resolve() == (BUILD_DIR / "plant").resolve()
