"""Reference scores as data: the reward per step of the benchmark's reference
(``reference``, normalized score 1) and of all valves closed (``closed``, 0) in
every scenario, seed and interval of a benchmark, shipped with the project
(``scenarios/reference/*.json``, installed beside the scenarios) so a method is
scored without running the reference (``benchmark --reference-scores``).

A file holds, besides the rewards, what they depend on, and is used only where
all of it matches:

* ``code``: the digests of the code that made them: the SHA-256 of each Python
  module the reference's and closed's runs can execute (the import closure of
  their tools and agents, read from the code: :func:`python_modules`; a module
  outside it, a figure or the benchmark's report, changes without staling the
  file), and the digest of the native core's C++ sources (``cpp/plant/core/``
  and ``cpp/plant/bindings/``, every file: :func:`native_source_digest`; they
  include nothing else of the project, and the runs, made with ``--link core``,
  execute no other C++: the LCM plant, its bus and tools are not keyed; the built
  binary differs between two builds of the same sources, which embed the
  build's paths, so the sources are hashed instead);
* ``protocol``: intervals, steps per interval, link;
* per scenario, the SHA-256 of the scenario file's text.

A disagreement is refused with one line naming what differs
(:class:`ReferenceScoresError`).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import hashlib
import json
from pathlib import Path
from typing import Any, Mapping, Sequence

from ftc.common.atomic import atomic_write_json, atomic_write_text
from ftc.common.paths import PACKAGE_DIR, REPO_ROOT
from ftc.common.source_key import native_source_digest
from ftc.control import registry
from ftc.experiments.import_closure import closure

REFERENCE = "reference"
CLOSED = "closed"
METHODS = (REFERENCE, CLOSED)
# The built binaries (the native core, the plant) are not keyed: two builds of one
# commit differ (measured: _core of the same commit built in two checkouts, two
# digests), so shipped data is keyed by their sources instead.
BUILT = ("_core", "plant")
LINK = "core"  # the only link reference scores are made with (the native core in process)
SHIPPED = "shipped"  # --reference-scores shipped: the file for the default suite
PROTOCOL = ("intervals", "steps_per_interval", "link")  # run settings the rewards depend on


class ReferenceScoresError(ValueError):
    """Reference scores that do not apply here; the message names the difference."""


def entry_modules() -> list[str]:
    """The modules the reference's and closed's runs start from: each method's tool
    (run with ``python -m``) and its agent's module (named in the registry as a
    string, so no import statement leads there)."""
    out = []
    for name in METHODS:
        method = registry.METHODS[name]
        out += [method.tool, method.agent.split(":")[0]]
    return sorted(set(out))


def python_modules(package_dir: Path | None = None) -> dict[str, Path]:
    """"ftc/<path>" -> source file of every module of the import closure of
    :func:`entry_modules` in ``package_dir`` (default: this package)."""
    package_dir = PACKAGE_DIR if package_dir is None else Path(package_dir)
    return {f"ftc/{path.relative_to(package_dir).as_posix()}": path
            for path in closure(entry_modules(), package_dir).values()}


def code_key(root: Path | None = None) -> dict[str, str]:
    """What reference rewards depend on of the code: the SHA-256 of each module of
    :func:`python_modules` and the plant's C++ sources' digest ("native sources").
    ``root``: a checkout to hash (its ``python/ftc`` when it has one, else this
    package's; its ``cpp/plant``)."""
    package_dir = None
    if root is not None and (Path(root) / "python" / "ftc").is_dir():
        package_dir = Path(root) / "python" / "ftc"
    digests = {k: hashlib.sha256(p.read_bytes()).hexdigest()
               for k, p in python_modules(package_dir).items()}
    digests["native sources"] = native_source_digest(root) or ""
    return digests


def shipped_dir() -> Path:
    """scenarios/reference of the checkout, else of the installed package."""
    for d in (REPO_ROOT / "scenarios" / "reference", PACKAGE_DIR / "scenarios" / "reference"):
        if d.is_dir():
            return d
    return REPO_ROOT / "scenarios" / "reference"


def resolve(spec: str) -> Path:
    """``shipped`` (the default suite's file) or a path."""
    return shipped_dir() / "suite.json" if spec == SHIPPED else Path(spec)


def load(path: Path) -> dict:
    """A reference-scores file, its shape checked (ReferenceScoresError: one line)."""
    try:
        data = json.loads(Path(path).read_text())
        for stem, sc in data["scenarios"].items():
            for m in METHODS:
                for seed, values in sc["rewards"][m].items():
                    if not all(isinstance(v, (int, float)) for v in values):
                        raise ValueError(f"{stem} {m} seed {seed}: not numbers")
        data["code"], data["protocol"]  # noqa: B018 (their presence is checked)
    except OSError as e:
        raise ReferenceScoresError(f"reference scores {path}: cannot read ({e.strerror or e})")
    except (ValueError, KeyError, TypeError, AttributeError) as e:
        raise ReferenceScoresError(f"reference scores {path}: not a reference-scores file "
                                   f"({type(e).__name__}: {e})")
    return data


def check(data: Mapping, path: Path, protocol: Mapping, scenarios: Mapping[str, str],
          seeds: tuple[int, ...], code: Mapping[str, str] | None = None) -> None:
    """ReferenceScoresError naming the first thing in which ``data`` does not apply:
    the code (``code``: default :func:`code_key`), the protocol, a scenario's text
    (``scenarios``: stem -> TOML text) or a seed without rewards."""
    code = code_key() if code is None else code
    for k in sorted(set(code) | set(data["code"])):
        if code.get(k) != data["code"].get(k):
            raise ReferenceScoresError(
                f"reference scores {path}: made with other code ({k}: "
                f"{str(data['code'].get(k))[:12]} there, {str(code.get(k))[:12]} here); run "
                "the reference instead (without --reference-scores)")
    for k, v in protocol.items():
        if data["protocol"].get(k) != v:
            raise ReferenceScoresError(f"reference scores {path}: made with {k} "
                                       f"{data['protocol'].get(k)}, this benchmark has {v}")
    for stem, text in scenarios.items():
        sc = data["scenarios"].get(stem)
        if sc is None:
            raise ReferenceScoresError(f"reference scores {path}: no scenario {stem}")
        if sc["sha256"] != hashlib.sha256(text.encode()).hexdigest():
            raise ReferenceScoresError(f"reference scores {path}: scenario {stem}'s file "
                                       "differs from the one they were made on")
        for m in METHODS:
            missing = [s for s in seeds if str(s) not in sc["rewards"][m]]
            if missing:
                raise ReferenceScoresError(f"reference scores {path}: no {m} rewards for "
                                           f"scenario {stem}, seed {missing[0]}")


def rows(data: Mapping, scenarios: tuple[str, ...], seeds: tuple[int, ...]) -> list[dict]:
    """The reference's and closed's cells as results rows (scenario, method, seed,
    interval, reward_per_step)."""
    out = []
    for stem in scenarios:
        for m in METHODS:
            for seed in seeds:
                for k, v in enumerate(data["scenarios"][stem]["rewards"][m][str(seed)]):
                    out.append({"scenario": stem, "method": m, "seed": int(seed),
                                "interval": k, "reward_per_step": float(v)})
    return out


def from_benchmarks(run_dirs: Sequence[Path], out: Path) -> dict:
    """Write the reference-scores file of finished benchmark directories that ran
    ``reference`` and ``closed`` (their results.csv, scenario files and configs; a
    scenario's rewards may come from several, its file must be the same in each);
    only scenarios with every seed of both methods are written. The code key is
    this checkout's, so write it with the code that ran them."""
    scenarios: dict = {}
    protocol, seeds = None, None
    for run_dir in map(Path, run_dirs):
        config = json.loads((run_dir / "benchmark.json").read_text())["config"]
        mine = {k: config[k] for k in PROTOCOL}
        if protocol not in (None, mine):
            raise ReferenceScoresError(f"{run_dir}: protocol {mine}, not {protocol}")
        protocol, seeds = mine, config["seeds"]
        with open(run_dir / "results.csv", newline="") as f:
            for r in csv.DictReader(f):
                if r["method"] not in METHODS:
                    continue
                text = (run_dir / "scenarios" / f"{r['scenario']}.toml").read_text()
                sha = hashlib.sha256(text.encode()).hexdigest()
                sc = scenarios.setdefault(r["scenario"], {"sha256": sha, "rewards": {
                    m: {} for m in METHODS}})
                if sc["sha256"] != sha:
                    raise ReferenceScoresError(f"{run_dir}: scenario {r['scenario']}'s file "
                                               "differs from another directory's")
                sc["rewards"][r["method"]].setdefault(r["seed"], {})[int(r["interval"])] = \
                    float(r["reward_per_step"])
    if protocol and protocol["link"] != LINK:
        raise ReferenceScoresError(f"the benchmarks ran with --link {protocol['link']}; "
                                   f"reference scores are keyed by the native core's sources "
                                   f"only: make them with --link {LINK}")
    complete = {}
    for stem, sc in scenarios.items():
        if any(str(s) not in sc["rewards"][m] for m in METHODS for s in seeds):
            continue
        for m in METHODS:
            for seed, per in list(sc["rewards"][m].items()):
                if sorted(per) != list(range(int(protocol["intervals"]))):
                    raise ReferenceScoresError(f"{m} in {stem}, seed {seed}, has not every "
                                               "interval")
                sc["rewards"][m][seed] = [per[k] for k in sorted(per)]
        complete[stem] = sc
    if not complete:
        raise ReferenceScoresError("no scenario has every seed of both methods")
    data = {"what": "reward per step of the reference and of all valves closed, per "
                    "scenario, seed (key) and interval (list position)",
            "code": code_key(), "protocol": protocol, "scenarios": dict(sorted(complete.items()))}
    atomic_write_json(Path(out), data)
    return data


# ---------------------------------------------------------------------------
# The benchmark's hooks (ftc.experiments.benchmark)
# ---------------------------------------------------------------------------

RUN_FILE = "reference_scores.json"  # the run directory's copy of the file given


def add_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--reference-scores", default=None, metavar="FILE",
                        help=f"take {REFERENCE}'s and {CLOSED}'s rewards from this file "
                             f"('{SHIPPED}': the default suite's, scenarios/reference/"
                             "suite.json) instead of running them; refused when it was made "
                             "with other code, protocol or scenario files")


def from_args(parser: argparse.ArgumentParser, args: argparse.Namespace, base: Any,
              texts: Mapping[str, tuple[str, str]], seeds: Sequence[int]) -> Any:
    """The benchmark's config (``base``, a BenchmarkConfig) with ``reference_scores``
    set to the --reference-scores file, checked against it (exit 2 with one line
    where it does not apply); ``base`` itself without the option."""
    if args.reference_scores is None:
        return base
    if args.resume:
        parser.error("--reference-scores starts a benchmark; a resumed one keeps its own")
    if base.reference != REFERENCE:
        parser.error(f"--reference-scores: they score against {REFERENCE}, not "
                     f"--reference {base.reference}")
    path = resolve(args.reference_scores)
    try:
        check(load(path), path, {k: getattr(base, k) for k in PROTOCOL},
              {stem: text for stem, (_, text) in texts.items()}, tuple(int(s) for s in seeds))
    except ReferenceScoresError as e:
        parser.error(f"--reference-scores: {e}")
    return dataclasses.replace(base, reference_scores=str(path))


def given(config: Any) -> tuple[str, ...]:
    """The methods whose cells a benchmark takes from its file (none without one)."""
    return METHODS if config.reference_scores else ()


def copy_into(out: Path, config: Any) -> Any:
    """The file given copied into the run directory (``RUN_FILE``), the config naming
    that copy; the config unchanged without a file or once copied."""
    if not config.reference_scores or config.reference_scores == RUN_FILE:
        return config
    atomic_write_text(Path(out) / RUN_FILE, Path(config.reference_scores).read_text())
    return dataclasses.replace(config, reference_scores=RUN_FILE)


def cells_of(out: Path, config: Any) -> list[dict]:
    """The reference's and closed's cells of a benchmark from its copy of the file
    (none without one)."""
    if not config.reference_scores:
        return []
    return rows(load(Path(out) / RUN_FILE), config.scenarios, config.seeds)
