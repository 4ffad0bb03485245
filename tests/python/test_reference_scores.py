"""Reference scores as data (ftc.experiments.reference_scores): keyed by the
plant's C++ sources and the Python modules the reference's and closed's runs
execute (their import closure); a one-byte change of the plant code in a copy
is refused, a module outside the closure changes nothing; a benchmark with --reference-scores runs
neither the reference nor closed and scores a method from the file's rewards."""

from __future__ import annotations

import csv
import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from ftc.common import source_key
from ftc.experiments import benchmark, reference_scores

REPO = Path(__file__).resolve().parents[2]


def _copy_plant(tmp_path: Path) -> Path:
    root = tmp_path / "checkout"
    shutil.copytree(REPO / "cpp" / "plant", root / "cpp" / "plant")
    return root


def _file(path: Path, code: dict, rewards: dict, text: str, intervals: int = 2,
          steps: int = 16) -> Path:
    path.write_text(json.dumps({
        "code": code, "protocol": {"intervals": intervals, "steps_per_interval": steps,
                                   "link": "core"},
        "scenarios": {"single": {"sha256": hashlib.sha256(text.encode()).hexdigest(),
                                 "rewards": rewards}}}))
    return path


def test_one_byte_of_the_plant_code_changed_is_refused(tmp_path):
    root = _copy_plant(tmp_path)
    made = reference_scores.code_key(root)
    assert made == reference_scores.code_key()  # the copy is the checkout's plant
    data = {"code": made, "protocol": {}, "scenarios": {}}
    reference_scores.check(data, Path("f.json"), {}, {}, ())  # the same code: accepted
    source = root / "cpp" / "plant" / "core" / "plant.cpp"
    body = bytearray(source.read_bytes())
    body[len(body) // 2] ^= 1  # one byte, one bit
    source.write_bytes(bytes(body))
    with pytest.raises(reference_scores.ReferenceScoresError) as e:
        reference_scores.check(data, Path("f.json"), {}, {}, (),
                               code=reference_scores.code_key(root))
    assert "made with other code (native sources:" in str(e.value)
    assert "\n" not in str(e.value)


def test_a_new_plant_file_changes_the_key_and_the_built_binaries_do_not_count(tmp_path):
    root = _copy_plant(tmp_path)
    before = reference_scores.native_source_digest(root)
    (root / "cpp" / "plant" / "core" / "new.h").write_text("// new\n")
    assert reference_scores.native_source_digest(root) != before
    assert not set(reference_scores.code_key()) & set(reference_scores.BUILT)


def test_the_native_key_is_the_cores_sources_and_they_include_nothing_else(tmp_path):
    import re

    root = _copy_plant(tmp_path)
    before = reference_scores.native_source_digest(root)
    _edit(root / "cpp" / "plant" / "lcm" / "signing.h", "// the bus\n")  # not the core's
    _edit(root / "cpp" / "plant" / "apps" / "echo.cpp", "// a tool\n")
    assert reference_scores.native_source_digest(root) == before
    _edit(root / "cpp" / "plant" / "bindings" / "bindings.cpp", "// bound\n")
    assert reference_scores.native_source_digest(root) != before
    # what the key covers is the include closure of the core's sources: every
    # project header they include is under NATIVE_DIRS
    base = REPO / "cpp" / "plant"
    for d in source_key.NATIVE_DIRS:
        for source in (base / d).rglob("*"):
            for header in re.findall(r'#include "([^"]+)"', source.read_text()):
                assert header.split("/")[:2] in (["plant", x] for x in
                                                 source_key.NATIVE_DIRS), (source, header)


def _copy_package(tmp_path: Path) -> Path:
    root = _copy_plant(tmp_path)
    shutil.copytree(REPO / "python" / "ftc", root / "python" / "ftc",
                    ignore=shutil.ignore_patterns("__pycache__", "*.so"))
    return root


def _edit(path: Path, text: str = "\n# edited\n") -> None:
    path.write_text(path.read_text() + text)


def test_the_key_is_the_import_closure_of_the_reference_and_closed_runs(tmp_path):
    root = _copy_package(tmp_path)
    made = reference_scores.code_key(root)
    assert made == reference_scores.code_key()  # the copy is the checkout's code
    modules = set(reference_scores.python_modules())
    # the runs' tools, agents, planner and reward are in; plotting and the benchmark are not
    for name in ("ftc/mpc.py", "ftc/controller.py", "ftc/control/agents/baselines.py",
                 "ftc/control/agents/physics/mpc.py", "ftc/plant/reward.py",
                 "ftc/control/planning/physics/episode_planner.py", "ftc/__init__.py"):
        assert name in modules, name
    for name in ("ftc/experiments/figures.py", "ftc/experiments/benchmark.py",
                 "ftc/experiments/reference_scores.py"):
        assert name not in modules, name
    data = {"code": made, "protocol": {}, "scenarios": {}}
    package = root / "python" / "ftc"
    _edit(package / "experiments" / "figures.py")  # a plotting module: the key holds
    reference_scores.check(data, Path("f.json"), {}, {}, (), code=reference_scores.code_key(root))
    _edit(package / "plant" / "reward.py")  # a module the runs execute: refused, named
    with pytest.raises(reference_scores.ReferenceScoresError) as e:
        reference_scores.check(data, Path("f.json"), {}, {}, (),
                               code=reference_scores.code_key(root))
    assert "made with other code (ftc/plant/reward.py:" in str(e.value)
    # a closure module that starts importing a plotting module brings it in
    _edit(package / "plant" / "valves.py", "\n\ndef _f():\n    from ftc.experiments import figures\n")
    grown = reference_scores.code_key(root)
    assert set(grown) - set(made) >= {"ftc/experiments/figures.py",
                                      "ftc/experiments/__init__.py"}


def test_the_closure_follows_every_kind_of_import(tmp_path):
    from ftc.experiments.import_closure import closure

    pkg = tmp_path / "ftc"
    files = {"__init__.py": "", "a/__init__.py": "from .b import x\n",
             "a/b.py": "x = 1\ndef f():\n    import ftc.c.d\n",
             "c/__init__.py": "", "c/d.py": "from ftc.e import g, h\n",
             "e/__init__.py": "from . import g\n", "e/g.py": "from ..a import b\n",
             "f.py": "import os\nfrom ftc import _core\n", "unused.py": "import ftc.f\n",
             "msg_t.py": '"""LCM type definitions\n"""\n'}
    for name, text in files.items():
        (pkg / name).parent.mkdir(parents=True, exist_ok=True)
        (pkg / name).write_text(text)
    got = closure(["ftc.a"], pkg)
    # ftc.a -> .b (relative) -> ftc.c.d (in a function, with its parents) -> ftc.e
    # (its __init__ imports .g) and g (a submodule named by a from-import) -> ..a.b;
    # h is an attribute, f and unused are imported by no one reached
    assert sorted(got) == ["ftc", "ftc.a", "ftc.a.b", "ftc.c", "ftc.c.d", "ftc.e", "ftc.e.g"]
    assert got["ftc.e.g"] == pkg / "e" / "g.py"
    # the native core has no source, lcm-gen's classes are left out
    assert sorted(closure(["ftc.f", "ftc.msg_t"], pkg)) == ["ftc", "ftc.f"]
    with pytest.raises(ValueError, match="no source file for entry module 'ftc.zz'"):
        closure(["ftc.zz"], pkg)


def _scenario(tmp_path: Path) -> tuple[Path, str]:
    path = tmp_path / "single.toml"
    text = (REPO / "scenarios" / "single.toml").read_text().replace(
        "steps_per_interval = 512", "steps_per_interval = 16")
    path.write_text(text)
    return path, text


@pytest.mark.slow  # a real balance run, about 5 s idle and 20 s on a loaded machine
def test_a_benchmark_scored_from_the_file_runs_no_reference(tmp_path):
    scenario, text = _scenario(tmp_path)
    # rewards per step by interval: the reference 3.0 then 3.0, closed 3.0 then 1.0
    rewards = {"reference": {"0": [3.0, 3.0]}, "closed": {"0": [3.0, 1.0]}}
    scores = _file(tmp_path / "scores.json", reference_scores.code_key(), rewards, text)
    out = tmp_path / "out"
    proc = subprocess.run(
        [sys.executable, "-m", "ftc.experiments", "benchmark", "--scenarios", str(scenario),
         "--methods", "balance", "--seeds", "0", "--intervals", "2",
         "--steps-per-interval", "16", "--jobs", "1", "--reference-scores", str(scores),
         "--run-cache", "", "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert sorted(p.name for p in (out / "runs" / "single" / "t00").iterdir()) == ["balance"]
    with open(out / "results.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    balance = {int(r["interval"]): r for r in rows if r["method"] == "balance"}
    r1 = float(balance[1]["reward_per_step"])
    # (r - closed) / (reference - closed) with the file's rewards of interval 1
    assert float(balance[1]["normalized_score"]) == pytest.approx((r1 - 1.0) / (3.0 - 1.0))
    assert float(balance[1]["reference_reward_per_step"]) == 3.0
    assert {r["method"] for r in rows} == {"balance", "reference", "closed"}
    assert (out / "report.md").is_file()


@pytest.mark.parametrize("change, message", [
    ("code", "made with other code (native sources:"),
    ("protocol", "made with intervals 3, this benchmark has 2"),
    ("scenario", "scenario single's file differs"),
    ("seed", "no reference rewards for scenario single, seed 0"),
])
def test_a_file_that_does_not_apply_is_refused_in_one_line(tmp_path, capsys, change, message):
    scenario, text = _scenario(tmp_path)
    code = dict(reference_scores.code_key())
    rewards = {"reference": {"0": [3.0, 3.0]}, "closed": {"0": [3.0, 1.0]}}
    if change == "code":
        code["native sources"] = "0" * 64
    if change == "seed":
        rewards = {"reference": {"1": [3.0, 3.0]}, "closed": {"1": [3.0, 1.0]}}
    scores = _file(tmp_path / "scores.json", code, rewards,
                   text + "\n" if change == "scenario" else text,
                   intervals=3 if change == "protocol" else 2)
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as e:
        benchmark.parse_args(["--scenarios", str(scenario), "--methods", "balance", "--seeds",
                              "0", "--intervals", "2", "--steps-per-interval", "16",
                              "--reference-scores", str(scores), "--out", str(out)])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not out.exists()


def test_the_install_writes_the_digest_the_checkout_computes(tmp_path):
    # an installed package has no C++ sources: its install (CMakeLists.txt, SKBUILD)
    # runs cpp/cmake/native_sources.cmake, which must agree with Python's digest,
    # on the checkout and on a copy with one byte changed
    root = _copy_plant(tmp_path)
    header = root / "cpp" / "plant" / "core" / "plant.h"
    body = bytearray(header.read_bytes())
    body[100] ^= 1
    header.write_bytes(bytes(body))
    for checkout in (REPO, root):
        out = tmp_path / f"{checkout.name}.sha256"
        subprocess.run(["cmake", f"-DFTC_SOURCE_DIR={checkout}", f"-DFTC_DIGEST_OUT={out}",
                        "-P", str(REPO / "cpp" / "cmake" / "native_sources.cmake")], check=True)
        assert out.read_text().strip() == reference_scores.native_source_digest(checkout)
    assert (tmp_path / "checkout.sha256").read_text() != \
        (tmp_path / f"{REPO.name}.sha256").read_text()


def test_the_shipped_file_covers_the_default_suite_and_its_scenario_files():
    from ftc.experiments.suite import default_suite

    data = reference_scores.load(reference_scores.resolve(reference_scores.SHIPPED))
    assert data["protocol"] == {"intervals": 10, "steps_per_interval": 512, "link": "core"}
    for sc in default_suite():
        entry = data["scenarios"][sc.name]
        assert entry["sha256"] == hashlib.sha256(sc.toml(512).encode()).hexdigest()
        for m in reference_scores.METHODS:
            assert sorted(entry["rewards"][m]) == ["0", "1", "2"]
            assert all(len(v) == 10 for v in entry["rewards"][m].values())
        # the reference never earns less than closed over intervals 1-9
        ref, closed = entry["rewards"]["reference"]["0"], entry["rewards"]["closed"]["0"]
        assert sum(ref[1:]) > sum(closed[1:])


def test_reference_scores_are_made_with_the_link_whose_code_they_key(tmp_path):
    # the key holds the native core's sources, not the LCM plant's: a benchmark
    # over LCM is refused as a source, in one line
    run = tmp_path / "bench"
    run.mkdir()
    (run / "benchmark.json").write_text(json.dumps({"config": {
        "intervals": 2, "steps_per_interval": 16, "link": "lcm", "seeds": [0]}}))
    (run / "results.csv").write_text("scenario,method,seed,interval,reward_per_step\n")
    with pytest.raises(reference_scores.ReferenceScoresError, match="make them with --link core"):
        reference_scores.from_benchmarks([run], tmp_path / "out.json")
    assert not (tmp_path / "out.json").exists()
