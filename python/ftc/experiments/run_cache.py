"""A cache of finished runs for the methods whose results depend on nothing
but the scenario (``cached=True`` in :mod:`ftc.control.registry`: the
``reference`` planner on the true physics). The benchmark runs such a method
once per scenario, copies the run to every seed, and keeps it here, so a
later benchmark of the same scenario bytes with the same code runs
nothing.

A run's key is the SHA-256 of: the scenario file's text, the method's command
line arguments, the run settings (intervals, steps per interval, link), the
seed when the scenario's plant draws random numbers (sensor noise, a random
start; otherwise none) and the digests of the code that runs (every Python
source of the package, the built native core and the plant executable:
:func:`code_digests`). A changed byte of any of them misses.

Layout: ``DIR/<key>/run/`` (the run directory as the benchmark wrote it) and
``DIR/<key>/key.json`` (what the key was made of). An entry is written in a
temporary directory and renamed into place, so a reader never sees half of one.

The benchmark's side: :func:`cache_groups` groups its runs by key,
:func:`reuse_before` fills a group from a finished run or the cache before the
pool starts, :func:`reuse_after` keeps the group's run and copies it to the rest.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

from ftc.common.atomic import atomic_write_json
from ftc.common.build_info import BuildMissingError, plant_binary
from ftc.experiments.method_args import method_args
from ftc.experiments.methods import METHODS
from ftc.experiments.runs import RunSpec, is_finished

ENV = "FTC_RUN_CACHE"  # overrides the default directory ('' disables the cache)
DEFAULT_DIR = "~/.cache/ftc/reference"


def default_dir() -> Path | None:
    """$FTC_RUN_CACHE if set ('' : None, no cache), else ~/.cache/ftc/reference."""
    value = os.environ.get(ENV, DEFAULT_DIR)
    return Path(value).expanduser() if value else None


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def package_digest(package: Path) -> str:
    """SHA-256 over every Python source of the package directory ``package``
    (each file's path relative to it and its bytes, in sorted order): every module
    a cached run can import, whichever it does (the interval runner, the lockstep
    loop that computes the reward and the episode ends, the planners, the reward)."""
    h = hashlib.sha256()
    for path in sorted(package.rglob("*.py")):
        h.update(path.relative_to(package).as_posix().encode() + b"\0")
        h.update(_sha256(path).encode())
    return h.hexdigest()


def code_digests(package: Path | None = None) -> dict[str, str]:
    """The digests of the code a cached run executes: every Python source of the
    ftc package (:func:`package_digest`; ``package`` defaults to this one), the
    built native core (``_core``, whose bytes carry the C++ physics and batch
    rollouts) and the plant executable (the LCM link's plant; absent: '')."""
    from ftc import _core  # native: its shared library is hashed, not run

    try:
        plant = _sha256(plant_binary())
    except BuildMissingError:
        plant = ""
    return {"ftc": package_digest(package or Path(__file__).resolve().parents[1]),
            "_core": _sha256(Path(_core.__file__)), "plant": plant}


def scenario_is_random(path: Path) -> bool:
    """Whether the plant draws random numbers under this scenario (its results then
    depend on the seed): sensor noise or a random start."""
    from ftc import _core  # native: the plant's own scenario parser

    sc = _core.load_scenario(str(path))
    return sc.noise_std > 0 or sc.random_start


@dataclass(frozen=True)
class RunKey:
    """What a cached run's results depend on; ``digest`` names its entry."""

    scenario_text: str
    args: tuple[str, ...]
    intervals: int
    steps_per_interval: int
    link: str
    seed: int | None  # None: the plant draws no random numbers, every seed is one run
    code: tuple[tuple[str, str], ...]  # (file, SHA-256) pairs

    def to_json(self) -> dict:
        return {"scenario_sha256": hashlib.sha256(self.scenario_text.encode()).hexdigest(),
                "args": list(self.args), "intervals": self.intervals,
                "steps_per_interval": self.steps_per_interval, "link": self.link,
                "seed": self.seed, "code": dict(self.code)}

    @property
    def digest(self) -> str:
        doc = {**self.to_json(), "scenario_text": self.scenario_text}
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()


class RunCache:
    """Finished runs by :class:`RunKey`, in ``root`` (None: a cache that holds nothing)."""

    def __init__(self, root: Path | None) -> None:
        self.root = None if root is None else Path(root).expanduser()

    def entry(self, key: RunKey) -> Path | None:
        return None if self.root is None else self.root / key.digest

    def restore(self, key: RunKey, run_dir: Path) -> bool:
        """Copy the cached run into ``run_dir`` (replacing what is there); False on a miss."""
        entry = self.entry(key)
        if entry is None or not (entry / "run" / "result.json").is_file():
            return False
        if run_dir.exists():
            shutil.rmtree(run_dir)
        run_dir.parent.mkdir(parents=True, exist_ok=True)
        shutil.copytree(entry / "run", run_dir)
        return True

    def store(self, key: RunKey, run_dir: Path) -> bool:
        """Keep a copy of the finished ``run_dir``; False when there is no cache or
        the entry exists already. OSError: the cache cannot be written."""
        entry = self.entry(key)
        if entry is None or entry.exists():
            return False
        self.root.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{key.digest[:12]}-", dir=self.root))
        try:
            shutil.copytree(run_dir, tmp / "run", ignore=shutil.ignore_patterns("processes.json"))
            (tmp / "key.json").write_text(json.dumps(key.to_json(), indent=1, sort_keys=True))
            os.rename(tmp, entry)  # atomic; another writer's entry first: keep that one
        except OSError:
            shutil.rmtree(tmp, ignore_errors=True)
            if entry.exists():
                return False
            raise
        return True


def cache_groups(out: Path, runs: list[RunSpec], intervals: int, steps_per_interval: int,
                 link: str, controller_args: tuple[str, ...]) -> dict[RunKey, list[RunSpec]]:
    """The runs of the cached methods (registry ``cached``) of a benchmark in
    ``out``, grouped by what their results depend on (:class:`RunKey`): one group
    per scenario, or per scenario and seed where the scenario's plant draws
    random numbers."""
    code = tuple(sorted(code_digests().items()))
    random: dict[str, bool] = {}
    groups: dict[RunKey, list[RunSpec]] = {}
    for r in runs:
        spec = METHODS[r.method]
        if not spec.cached:
            continue
        path = out / "scenarios" / f"{r.scenario}.toml"
        if r.scenario not in random:
            random[r.scenario] = scenario_is_random(path)
        key = RunKey(path.read_text(), (*spec.args, *method_args(spec, controller_args)),
                     intervals, steps_per_interval, link,
                     r.seed if random[r.scenario] else None, code)
        groups.setdefault(key, []).append(r)
    return groups


def copy_run(source: Path, spec: RunSpec, out: Path, reused: dict) -> None:
    """A finished run's directory as ``spec``'s, its result.json naming where it
    came from (``reused``); result.json is written last, as a run's is."""
    target = spec.directory(out)
    if source != target:
        if target.exists():
            shutil.rmtree(target)
        shutil.copytree(source, target, ignore=shutil.ignore_patterns("result.json",
                                                                       "processes.json"))
    record = json.loads((source / "result.json").read_text())
    record.update(run=spec.key, seed=spec.seed, reused=reused)
    atomic_write_json(target / "result.json", record)


def reuse_before(out: Path, groups: dict[RunKey, list[RunSpec]], finished: set[str],
                 cache: RunCache, sources: dict[str, dict]) -> set[str]:
    """Fill each group from a run of it already finished or from the cache (adding
    them to ``finished``, recording in ``sources`` where each came from); returns
    the runs to skip: a group with neither runs its first run, the others wait for it."""
    waiting = set()
    for key, group in groups.items():
        done = [r for r in group if r.key in finished]
        if not done and cache.restore(key, group[0].directory(out)):
            copy_run(group[0].directory(out), group[0], out, {"cache": key.digest})
            sources[group[0].key] = {"cache": key.digest, "from": "cache"}
            done = [group[0]]
        if not done:
            waiting |= {r.key for r in group[1:]}
            continue
        for r in group:
            if r.key not in finished and r is not done[0]:
                copy_run(done[0].directory(out), r, out, {"cache": key.digest,
                                                            "from": done[0].key})
                sources[r.key] = {"cache": key.digest, "from": done[0].key}
        finished.update(r.key for r in group)
    return waiting


def reuse_after(out: Path, groups: dict[RunKey, list[RunSpec]], cache: RunCache,
                sources: dict[str, dict], stream: TextIO, tool: str) -> None:
    """Keep each group's finished run in the cache and copy it to the group's waiting runs."""
    for key, group in groups.items():
        first = group[0].directory(out)
        if not is_finished(first):
            continue
        try:
            if cache.store(key, first):
                sources.setdefault(group[0].key, {"cache": key.digest, "from": "ran"})
        except OSError as e:
            print(f"{tool}: warning: cannot keep {group[0].key} in the cache {cache.root}: "
                  f"{e.strerror or e}", file=stream)
        for r in group[1:]:
            if not is_finished(r.directory(out)):
                copy_run(first, r, out, {"cache": key.digest, "from": group[0].key})
                sources[r.key] = {"cache": key.digest, "from": group[0].key}
