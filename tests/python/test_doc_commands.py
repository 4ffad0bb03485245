"""Every command of README.md and docs/*.md works as written, or says which
test runs its shorter equivalent (tests/python/doc_commands.py: the marks).

The ``run`` commands run here, in order, document by document, from a
scratch directory that sees the checkout's .venv, build, scenarios, examples
and scripts (so ``runs/...`` lands in the scratch directory, not the
checkout); the ``install`` ones run in tests/python/test_install.py. They are
kept short (an interval or two of 32-64 steps) so the whole file takes about
15 s."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

from doc_commands import DOCS, REPO, blocks, commands, mark_problem, marked

LINKED = (".venv", "build", "scenarios", "examples", "scripts")


def _rel(doc: Path) -> str:
    return doc.relative_to(REPO).as_posix()


def test_the_marks_are_read_and_a_wrong_one_is_found():
    text = ("<!-- commands: run -->\n```bash\n.venv/bin/python -m ftc.x \\\n    --a 1   # c\n"
            "# a comment\n\nls\n```\n```bash\nunmarked\n```\n")
    (first, body), (second, _) = blocks(text)
    assert first == "run" and second is None
    assert commands(body) == [".venv/bin/python -m ftc.x --a 1   # c", "ls"]
    assert mark_problem(second) and mark_problem("illustration") \
        and mark_problem("illustration; tested by tests/python/test_docs.py::no_such_test")
    assert mark_problem("illustration; tested by tests/python/test_docs.py::"
                        "test_history_is_found") is None
    (mark, body), = blocks("<!-- commands: run -->\n```python\nprint('a \\\\ b')\n```\n")
    assert mark == "run" and commands(body) == [
        ".venv/bin/python - <<'PYTHON'\nprint('a \\\\ b')\nPYTHON\n"]


@pytest.mark.parametrize("doc", DOCS, ids=_rel)
def test_every_command_block_is_run_by_a_test_or_names_the_test_of_its_equivalent(doc):
    problems = [f"block {i + 1}: {p}" for i, (mark, _) in enumerate(blocks(doc.read_text()))
                if (p := mark_problem(mark))]
    assert not problems, f"{_rel(doc)}: " + "; ".join(problems)


def test_the_install_commands_are_there_for_test_install():
    install = marked("install")
    assert install and all(c.startswith("myenv/bin/") for _, c in install), install


def test_the_run_commands_run_as_written(tmp_path):
    for name in LINKED:
        (tmp_path / name).symlink_to(REPO / name)
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")
    env.pop("FTC_BUILD_DIR", None)
    ran = marked("run")
    assert len(ran) >= 5, ran
    for doc, command in ran:
        done = subprocess.run(["bash", "-euo", "pipefail", "-c", command], cwd=tmp_path,
                              env=env, capture_output=True, text=True, timeout=300)
        assert done.returncode == 0, (f"{_rel(doc)}: {command}\nexit {done.returncode}\n"
                                      f"{done.stdout[-1500:]}\n{done.stderr[-1500:]}")
    assert (tmp_path / "runs" / "tb-demo.onnx").is_file()


def test_the_speed_scripts_take_the_documented_options():
    """docs/benchmarks.md's commands measure for minutes: their options exist."""
    for script, options in (("bench.py", ("--rounds", "--only", "--json", "--long")),
                            ("profile_run.py", ("controller_args",)),
                            ("bench_vector.py", ("--rounds", "--results", "--figure")),
                            ("bench_revisions.py", ("--before", "--after", "--only", "--rounds",
                                                    "--results"))):
        done = subprocess.run([str(REPO / ".venv" / "bin" / "python"),
                               str(REPO / "scripts" / script), "--help"],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 0 and all(o in done.stdout for o in options), done.stdout
