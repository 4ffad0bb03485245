"""A scenario goes by its packaged name (``single``, ``multiple``, ...) in every
tool as well as by a path (ftc.common.paths.scenario_file); the tools
themselves are run outside the checkout by tests/python/test_install.py."""

from __future__ import annotations

from pathlib import Path

import pytest

from ftc.common.paths import SCENARIO_DIR, scenario_file, scenario_names
from ftc.tools.plant import with_scenario_files


def test_a_name_is_the_packaged_file_and_a_path_stays_a_path(tmp_path, monkeypatch):
    assert scenario_names() == ["abrupt", "multiple", "nominal", "single"]
    assert Path(scenario_file("multiple")) == SCENARIO_DIR / "multiple.toml"
    assert scenario_file("") == ""  # the nominal plant
    assert scenario_file("my/own.toml") == "my/own.toml"  # checked later, as a file
    monkeypatch.chdir(tmp_path)
    (tmp_path / "single").write_text("")  # a file of that name here wins
    assert scenario_file("single") == "single"
    with pytest.raises(ValueError, match=r"unknown scenario name 'singel' .*known: abrupt, "
                                         r"multiple, nominal, single"):
        scenario_file("singel")


def test_ftc_plant_gives_the_plant_the_file_of_a_name():
    assert with_scenario_files(["--scenario", "abrupt", "--seed", "1"]) == [
        "--scenario", str(SCENARIO_DIR / "abrupt.toml"), "--seed", "1"]
    assert with_scenario_files(["--scenario=nominal"]) == [
        f"--scenario={SCENARIO_DIR / 'nominal.toml'}"]
    assert with_scenario_files(["--scenario", "x.toml", "--help"]) == [
        "--scenario", "x.toml", "--help"]
    with pytest.raises(ValueError, match="unknown scenario name 'nope'"):
        with_scenario_files(["--scenario", "nope"])
