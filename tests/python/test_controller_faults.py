"""The controller survives faults of its own (reliability issue, controller side),
through the real command line against the real plant where it can:

  * the plant killed mid-interval: one line "plant gone at interval K, step T",
    exit 3, metrics.csv and checkpoint.pt of the finished intervals intact, and
    --resume finishes the run with the results of an uninterrupted one;
  * an attached plant that stops answering: re-sent with exponential back-off,
    given up after --link-give-up-timeout;
  * a non-finite observation, loss, gradient or weight: exit 4 naming which and
    where, the last good checkpoint kept (in process, through a fake plant link);
  * a corrupt, truncated, foreign or mismatched checkpoint or config to --resume:
    exit 2 with the reason, nothing loaded or written;
  * a stop signal (SIGTERM, SIGINT, SIGHUP): one line, exit 128 + signal, the
    plant shut down, the finished intervals kept, --resume continues; SIGKILL:
    the plant dies with the controller;
  * the issue's done-when: a lockstep run through ftc.relay at 5% message loss
    gives metrics identical to a loss-free run with the same seed (2 short
    intervals here; the full 10 intervals are marked ``slow``).
"""

from __future__ import annotations

import dataclasses
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from forked_tools import run_tool
from proc_state import ended

import ftc.tools.controller as controller
import ftc.control.run.runner as runner
from ftc.common.build_info import plant_binary
from ftc.common.errors import NonFiniteError
from ftc.tools.controller import Controller, resume_config
from ftc.control.agents.ppo import ControllerConfig
from ftc.plant import CorePlant, private_lcm_url, private_prefix
from ftc.learning.ppo import PPOConfig

REPO = Path(__file__).resolve().parents[2]
PY = sys.executable
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(
    [str(REPO / "python"), str(REPO / "build" / "lcmtypes"), str(REPO / "build" / "python"),
     os.environ.get("PYTHONPATH", "")])}
TIME_COLUMNS = {"online_seconds", "offline_seconds", "wall_time"}
# the short run of test_controller.py (2 shortened intervals, small offline phase)
SHORT = ["--steps-per-interval", "128", "--update-every", "64", "--offline-steps", "512",
         "--offline-envs", "8", "--offline-rollout", "32", "--model-episodes", "6",
         "--seed", "3", "--quiet"]


def _short(out: Path, scenarios: Path, **kw) -> ControllerConfig:
    base = dict(out=str(out), intervals=2, steps_per_interval=128, update_every=64,
                offline_steps=512, offline_envs=8, offline_rollout=32, model_episodes=6,
                quiet=True, seed=3, link="core", scenario=str(scenarios / "single.toml"))
    base.update(kw)
    return ControllerConfig(**base)


def _wait_for(condition, what: str, timeout: float = 120.0, proc=None) -> None:
    """Poll a condition on the run directory (the fault's timing, not synchronisation
    of results: whatever step the kill lands on, the outcome asserted is the same)."""
    deadline = time.monotonic() + timeout
    while not condition():
        if proc is not None and proc.poll() is not None:
            raise AssertionError(f"controller exited ({proc.returncode}) before {what}: "
                                 f"{proc.stderr.read()}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.01)


def _rows(out: Path) -> int:
    try:
        return max(0, len((out / "metrics.csv").read_text().splitlines()) - 1)
    except FileNotFoundError:
        return 0


def _comparable(path: Path) -> list[str]:
    """metrics.csv without its wall-time columns, as text lines (exact comparison)."""
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    keep = [i for i, name in enumerate(header) if name not in TIME_COLUMNS]
    return [",".join(line.split(",")[i] for i in keep) for line in lines]


def _error_line(stderr: str) -> str:
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert len(lines) == 1, stderr
    assert lines[0].startswith("ftc.controller: error: "), lines[0]
    return lines[0]


def _snapshot(directory: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(directory.iterdir())}


# ---------------------------------------------------------------------------
# The plant stops answering
# ---------------------------------------------------------------------------

def test_plant_killed_mid_interval_exits_3_keeps_results_and_resumes(tmp_path, scenarios):
    out = tmp_path / "run"
    scenario = str(scenarios / "single.toml")
    # 512 steps per interval: interval 1 is still running when the kill lands
    args = [*SHORT, "--steps-per-interval", "512", "--update-every", "128", "--intervals", "2",
            "--scenario", scenario]
    proc = subprocess.Popen([PY, "-m", "ftc.controller", *args, "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV,
                            cwd=REPO)
    try:
        _wait_for(lambda: _rows(out) == 1, "interval 0 to finish", proc=proc)
        pid = int((out / "plant.pid").read_text())
        os.kill(pid, signal.SIGKILL)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 3
    line = _error_line(err)
    assert re.search(r"plant gone at interval 1, (evaluation )?step \d+: .*exited with code -9",
                     line), line
    # what was finished is kept, whole; nothing partial; nothing after it
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt", "config.json",
                                                      "metrics.csv"]
    assert _rows(out) == 1
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    assert state["interval"] == 1 and len(state["rows"]) == 1
    first_row = _comparable(out / "metrics.csv")

    resumed = subprocess.run([PY, "-m", "ftc.controller", "--resume", str(out), "--quiet"],
                             capture_output=True, text=True, env=ENV, cwd=REPO, timeout=300)
    assert resumed.returncode == 0, resumed.stderr
    assert _comparable(out / "metrics.csv")[:2] == first_row
    assert (out / "done.json").exists() and not (out / "plant.pid").exists()

    # nothing lost: the same as an uninterrupted run (a separate process, like the
    # runs above: in the test process the 9th digits of approx_kl differ)
    ref = subprocess.run([PY, "-m", "ftc.controller", *args, "--out", str(tmp_path / "ref")],
                         capture_output=True, text=True, env=ENV, cwd=REPO, timeout=300)
    assert ref.returncode == 0, ref.stderr
    assert _comparable(out / "metrics.csv") == _comparable(tmp_path / "ref" / "metrics.csv")


def _start_then_wait_for_an_interval(out: Path, scenario: str, ignoring: tuple[int, ...] = ()
                                     ) -> tuple[subprocess.Popen, int]:
    """``ignoring``: signals the controller starts with ignored, as a background
    job of a non-interactive shell starts with SIGINT ignored."""
    # 512 steps per interval: interval 1 is running when the signal lands; 6 intervals,
    # so that a test process descheduled on a loaded machine still signals a live run
    args = [*SHORT, "--steps-per-interval", "512", "--update-every", "128", "--intervals", "6",
            "--scenario", scenario]

    def ignore() -> None:
        for s in ignoring:
            signal.signal(s, signal.SIG_IGN)

    proc = subprocess.Popen([PY, "-m", "ftc.controller", *args, "--out", str(out)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV,
                            cwd=REPO, preexec_fn=ignore)
    _wait_for(lambda: _rows(out) == 1 and (out / "plant.pid").is_file(), "interval 0 to finish",
              proc=proc)
    return proc, int((out / "plant.pid").read_text())


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGHUP])
def test_a_stop_signal_shuts_the_plant_down_keeps_results_and_resumes(tmp_path, scenarios, sig):
    """SIGTERM (what a supervisor sends), SIGINT (Ctrl-C) and SIGHUP (a closed
    terminal) go through the run's clean-up: before, SIGTERM left the plant
    running for ever and plant.pid behind, and a signal landing in LCM's wait
    skipped the plant's shut-down. The controller starts with the signal
    ignored, as it is in a background job of a non-interactive shell (a CI
    runner): Python then installs no KeyboardInterrupt handler of its own, and
    before, SIGINT let the run finish and exit 0."""
    out = tmp_path / "run"
    proc, plant = _start_then_wait_for_an_interval(out, str(scenarios / "single.toml"),
                                                   ignoring=(sig,))
    try:
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 128 + sig, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert lines == [f"ftc.controller: stopped by {signal.Signals(sig).name}; the finished "
                     f"intervals are in {out}, --resume {out} continues"], err
    assert ended(plant), f"plant {plant} still running after the controller stopped"
    # the finished intervals, whole; no pid file, no temporary file
    assert sorted(p.name for p in out.iterdir()) == ["checkpoint.pt", "config.json",
                                                      "metrics.csv"]
    rows = _rows(out)
    assert rows >= 1 and torch.load(out / "checkpoint.pt", weights_only=True)["interval"] == rows
    if sig == signal.SIGTERM:
        resumed = subprocess.run([PY, "-m", "ftc.controller", "--resume", str(out), "--quiet"],
                                 capture_output=True, text=True, env=ENV, cwd=REPO, timeout=300)
        assert resumed.returncode == 0, resumed.stderr
        assert _rows(out) == 6 and (out / "done.json").exists()


def test_the_plant_dies_with_a_killed_controller(tmp_path, scenarios):
    """SIGKILL runs no clean-up: the plant, launched from the controller's main
    thread with PR_SET_PDEATHSIG, goes with it instead of waiting for commands
    for ever."""
    proc, plant = _start_then_wait_for_an_interval(tmp_path / "run",
                                                   str(scenarios / "single.toml"))
    proc.kill()
    proc.communicate(timeout=60)
    assert ended(plant), f"plant {plant} outlived its SIGKILLed controller"


def test_attached_plant_that_stops_answering_is_retried_with_backoff(tmp_path, scenarios):
    url, prefix = private_lcm_url(), private_prefix()
    out = tmp_path / "run"
    plant = subprocess.Popen([str(plant_binary()), "--lcm-url", url, "--prefix", prefix,
                              "--scenario", str(scenarios / "single.toml"), "--seed", "3",
                              "--steps-per-interval", "512"], stdout=subprocess.DEVNULL)
    proc = subprocess.Popen(
        [PY, "-m", "ftc.controller", "--seed", "3", "--quiet", "--steps-per-interval", "512",
         "--update-every", "128", "--no-offline", "--intervals", "3", "--scenario", str(scenarios / "single.toml"),
         "--attach", "--lcm-url", url, "--prefix", prefix, "--link-retry-timeout", "0.05",
         "--link-backoff", "2", "--link-give-up-timeout", "1.5", "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV, cwd=REPO)
    try:
        _wait_for(lambda: _rows(out) == 1, "interval 0 to finish", proc=proc)
        plant.kill()  # not the controller's child: only the silence tells
        killed = time.monotonic()
        _, err = proc.communicate(timeout=60)
        elapsed = time.monotonic() - killed
    finally:
        for p in (proc, plant):
            if p.poll() is None:
                p.kill()
            p.wait()
    assert proc.returncode == 3
    line = _error_line(err)
    # re-sent after 0.05, 0.15, 0.35, 0.75 s (waits 0.05 x 2^n), given up at 1.5 s
    assert re.search(r"plant gone at interval 1, (evaluation )?step \d+: .*did not answer .* "
                     r"within 1\.5 s after [34] re-sends", line), line
    assert 1.4 < elapsed < 10
    assert _rows(out) == 1
    assert torch.load(out / "checkpoint.pt", weights_only=True)["interval"] == 1


# ---------------------------------------------------------------------------
# Non-finite numbers
# ---------------------------------------------------------------------------

class NaNPlant:
    """A core plant whose observation turns NaN at one operating step."""

    def __init__(self, inner: CorePlant, at_operating_step: int) -> None:
        self.inner, self.at = inner, at_operating_step

    def reset(self):
        return self.inner.reset()

    def evaluate(self):
        return self.inner.evaluate()

    def step(self, valves):
        o = self.inner.step(valves)
        if not o.evaluation and o.operating_steps == self.at:
            level = o.level.copy()
            level[2] = np.nan
            o = dataclasses.replace(o, level=level)
        return o

    def close(self) -> None:
        pass


def _core(cfg: ControllerConfig) -> CorePlant:
    return CorePlant(cfg.scenario, cfg.seed, steps_per_interval=cfg.steps_per_interval)


def test_nan_observation_stops_the_run_and_keeps_the_last_good_checkpoint(tmp_path, scenarios):
    cfg = _short(tmp_path, scenarios, intervals=3)
    with pytest.raises(NonFiniteError, match=r"non-finite observation at interval 1, step 10: "
                                             r"levels \[.*nan"):
        Controller(cfg, PPOConfig()).run(plant=NaNPlant(_core(cfg), 128 + 10))
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert state["interval"] == 1
    assert all(torch.isfinite(t).all() for t in state["agent"]["ppo"]["policy"].values())
    assert _rows(tmp_path) == 1 and not (tmp_path / "done.json").exists()
    # the kept checkpoint resumes (the plant healthy again)
    cfg, ppo = resume_config(str(tmp_path))
    assert len(Controller(cfg, ppo).run()) == 3


@pytest.mark.parametrize("fault,message", [
    ("loss", r"non-finite loss in the PPO update at interval 1, step 64: value_loss = nan"),
    ("gradient", r"non-finite gradient in the PPO update at interval 1, step 64 \(trunk"),
    ("weights", r"non-finite weights after the PPO update at interval 1, step 64 \(trunk"),
])
def test_nan_loss_gradient_or_weights_stop_the_run(tmp_path, scenarios, fault, message):
    cfg = _short(tmp_path, scenarios, intervals=3)
    # the gradient check reads torch's .grad, which only the torch engine fills (the
    # native engine's gradients live in its kernels; a non-finite one shows in the
    # weights, the third case, which runs on the default engine)
    ctrl = Controller(cfg, PPOConfig(engine="torch" if fault == "gradient" else "native"))
    update = ctrl.ppo.update

    def faulty_update(buffer, last_values):
        stats = update(buffer, last_values)
        if ctrl.interval == 1:
            first = next(ctrl.ppo.policy.parameters())
            if fault == "loss":
                stats = stats._replace(value_loss=float("nan"))
            elif fault == "gradient":
                first.grad[0, 0] = float("inf")
            else:
                with torch.no_grad():
                    first[0, 0] = float("nan")
        return stats

    ctrl.ppo.update = faulty_update
    with pytest.raises(NonFiniteError, match=message):
        ctrl.run(plant=_core(cfg))
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    assert state["interval"] == 1
    assert all(torch.isfinite(t).all() for t in state["agent"]["ppo"]["policy"].values())


def test_cli_exits_4_on_a_nan_observation(tmp_path, scenarios, monkeypatch, capsys):
    monkeypatch.setattr(runner, "open_plant",
                        lambda cfg, start: NaNPlant(_core(cfg), 5))
    rc = controller.main([*SHORT, "--link", "core", "--scenario", str(scenarios / "single.toml"),
                          "--out", str(tmp_path)])
    assert rc == 4
    line = _error_line(capsys.readouterr().err)
    assert "non-finite observation at interval 0, step 5" in line
    assert not (tmp_path / "checkpoint.pt").exists() and not (tmp_path / "metrics.csv").exists()


# ---------------------------------------------------------------------------
# Corrupt and mismatched checkpoints
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def stopped_runs(tmp_path_factory, scenarios_dir=REPO / "scenarios"):
    """Runs stopped after 1 of 2 intervals: the base, and ones of other configurations."""
    root = tmp_path_factory.mktemp("stopped")
    variants = {"base": {}, "small_net": {}, "multiple": dict(scenario=str(
        scenarios_dir / "multiple.toml")), "closed": dict(method="closed")}
    for name, kw in variants.items():
        ppo = PPOConfig(trunk_sizes=(32, 32)) if name == "small_net" else PPOConfig()
        Controller(_short(root / name, scenarios_dir, **kw), ppo).run(stop_after=1)
    return root


def _torch_bytes(obj) -> bytes:
    import io

    buf = io.BytesIO()
    torch.save(obj, buf)
    return buf.getvalue()


CORRUPTIONS = {
    "truncated": (lambda good, other: good[: len(good) // 2], "corrupt or truncated checkpoint"),
    "random bytes": (lambda good, other: random.Random(0).randbytes(len(good)),
                     "corrupt or truncated checkpoint"),
    "empty": (lambda good, other: b"", "corrupt or truncated checkpoint"),
    "one byte flipped at the end": (
        lambda good, other: good[:-30] + bytes([good[-30] ^ 0xFF]) + good[-29:],
        "corrupt or truncated checkpoint"),
    "a pickled object": (lambda good, other: _torch_bytes({"x": argparse_namespace()}),
                         "corrupt or truncated checkpoint"),
    "not a checkpoint": (lambda good, other: _torch_bytes([1, 2, 3]),
                         "not a run checkpoint of this version"),
    "other network sizes": (lambda good, other: other["small_net"],
                            r"another configuration: ppo\.trunk_sizes \[32, 32\] in the "
                            r"checkpoint, \[64, 64\] here"),
    "other scenario": (lambda good, other: other["multiple"],
                       r"another configuration: controller\.scenario .*multiple\.toml"),
    "other method": (lambda good, other: other["closed"],
                     "another configuration: controller.method 'closed' in the checkpoint, "
                     "'ppo' here"),
}


def argparse_namespace():
    import argparse

    return argparse.Namespace(a=1)


@pytest.mark.parametrize("fault", list(CORRUPTIONS))
def test_bad_checkpoint_to_resume_exits_2_saying_why(tmp_path, stopped_runs, fault):
    run = tmp_path / "run"
    shutil.copytree(stopped_runs / "base", run)
    good = (run / "checkpoint.pt").read_bytes()
    others = {name: (stopped_runs / name / "checkpoint.pt").read_bytes()
              for name in ("small_net", "multiple", "closed")}
    corrupt, expected = CORRUPTIONS[fault]
    (run / "checkpoint.pt").write_bytes(corrupt(good, others))
    before = _snapshot(run)
    result = run_tool("ftc.controller", ["--resume", str(run)], cwd=REPO, env=ENV, timeout=60)
    assert result.returncode == 2, result.stderr
    line = _error_line(result.stderr)
    assert str(run / "checkpoint.pt") in line
    assert re.search(expected, line), line
    assert _snapshot(run) == before  # nothing loaded, nothing written


@pytest.mark.parametrize("config_text,expected", [
    ("{not json", "malformed run configuration"),
    ('{"controller": {"no_such_option": 1}, "ppo": {}}', "malformed run configuration"),
    (None, "missing"),
])
def test_bad_config_to_resume_exits_2(tmp_path, stopped_runs, config_text, expected):
    run = tmp_path / "run"
    shutil.copytree(stopped_runs / "base", run)
    if config_text is None:
        (run / "config.json").unlink()
    else:
        (run / "config.json").write_text(config_text)
    before = _snapshot(run)
    result = run_tool("ftc.controller", ["--resume", str(run)], cwd=REPO, env=ENV, timeout=60)
    assert result.returncode == 2
    line = _error_line(result.stderr)
    assert "config.json" in line and expected in line
    assert _snapshot(run) == before


# ---------------------------------------------------------------------------
# Done when: 5% message loss gives the same results as no loss
# ---------------------------------------------------------------------------

def _lossless_and_lossy(tmp_path: Path, scenario: Path, args: list[str], steps: int, seed: int,
                        loss: float = 0.05) -> tuple[Path, Path, dict, float]:
    """The same run twice: the controller launching its own plant, and attached
    through a relay dropping ``loss`` of the messages each way. Returns both run
    directories, the relay's counts and the lossy run's wall time."""
    clean, lossy = tmp_path / "clean", tmp_path / "lossy"
    common = [*args, "--scenario", str(scenario), "--seed", str(seed), "--quiet",
              "--steps-per-interval", str(steps), "--link-retry-timeout", "0.02"]
    result = subprocess.run([PY, "-m", "ftc.controller", *common, "--out", str(clean)],
                            capture_output=True, text=True, env=ENV, cwd=REPO, timeout=900)
    assert result.returncode == 0, result.stderr

    url, client, plant_prefix = private_lcm_url(), private_prefix(), private_prefix()
    plant = subprocess.Popen([str(plant_binary()), "--lcm-url", url, "--prefix", plant_prefix,
                              "--scenario", str(scenario), "--seed", str(seed),
                              "--steps-per-interval", str(steps)], stdout=subprocess.DEVNULL)
    relay = subprocess.Popen([PY, "-m", "ftc.relay", "--lcm-url", url, "--client-prefix",
                              client, "--plant-prefix", plant_prefix, "--loss", str(loss),
                              "--seed", "11"], stdout=subprocess.PIPE, text=True, env=ENV,
                             cwd=REPO)
    try:
        assert relay.stdout.readline().strip() == "ready"
        start = time.perf_counter()
        result = subprocess.run([PY, "-m", "ftc.controller", *common, "--attach", "--lcm-url",
                                 url, "--prefix", client, "--out", str(lossy)],
                                capture_output=True, text=True, env=ENV, cwd=REPO, timeout=900)
        wall = time.perf_counter() - start
        assert result.returncode == 0, result.stderr
    finally:
        relay.send_signal(signal.SIGTERM)
        counts_out, _ = relay.communicate(timeout=10)
        plant.terminate()
        plant.wait(timeout=10)
    counts = json.loads(counts_out.strip().splitlines()[-1])
    return clean, lossy, counts, wall


def test_short_run_at_5_percent_loss_equals_the_lossless_run(tmp_path, scenarios):
    clean, lossy, counts, _ = _lossless_and_lossy(
        tmp_path, scenarios / "single.toml",
        ["--intervals", "2", "--update-every", "64", *SHORT[4:12]], steps=128, seed=3)
    assert counts["dropped"] > 0
    assert _comparable(lossy / "metrics.csv") == _comparable(clean / "metrics.csv")


@pytest.mark.slow
def test_full_run_at_5_percent_loss_equals_the_lossless_run(tmp_path, scenarios):
    """The issue's done-when: 10 intervals of 512 steps, sequential offline mode."""
    clean, lossy, counts, wall = _lossless_and_lossy(
        tmp_path, scenarios / "single.toml", ["--intervals", "10"], steps=512, seed=0)
    print(f"\n5% loss: {counts}, lossy run {wall:.1f} s wall")
    assert counts["dropped"] > 100
    assert _comparable(lossy / "metrics.csv") == _comparable(clean / "metrics.csv")
    assert len(_comparable(lossy / "metrics.csv")) == 11
