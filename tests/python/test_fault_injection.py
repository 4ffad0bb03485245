"""Fault-injection suite: the plant and the tools around it survive faults of
their own and reject bad input clearly, losing nothing.

  * garbage, wrongly typed and truncated messages on the plant's channels:
    counted exactly, never a crash, the plant keeps serving;
  * out-of-range commands: rejected with a counted reason;
  * the plant killed under ftc.simulate: a clear error, exit 1, no CSV;
  * the controller of a real-time plant killed: the plant reaches its safe
    state within the watchdog time;
  * truncated and corrupted LCM logs to ftc.replay: one line naming the file
    and the byte offset, exit 2;
  * every malformed scenario file to the plant, ftc.simulate and ftc.mpc:
    one line naming the file and the key, exit 2, nothing written;
  * bad flags to every CLI: exit 2 naming the flag; an unwritable --out:
    exit 2 before any work;
  * security: no network URL without asking; no unpickling anywhere.

Every plant runs on a private port and prefix (ttl=0). Long variants are
marked ``slow`` (``pytest -m slow``). Set FTC_FAULT_TALLY=<file> to get the
counts of faults injected and malformed inputs tried as JSON lines.
"""

from __future__ import annotations

import json
import os
import random
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from forked_tools import run_tool

from ftc.common.build_info import plant_binary
from ftc.plant import (LinkConfig, PlantGoneError, check_loopback_url, launch, private_lcm_url,
                       private_prefix)

REPO = Path(__file__).resolve().parents[2]
PY = sys.executable
BAD_SCENARIOS = sorted((REPO / "tests" / "data").glob("bad_*.toml"))
ENV = {**os.environ, "PYTHONPATH": os.pathsep.join(
    [str(REPO / "python"), str(REPO / "build" / "lcmtypes"), str(REPO / "build" / "python"),
     os.environ.get("PYTHONPATH", "")])}


def tally(what: str, n: int) -> None:
    """Record n faults injected / malformed inputs tried (FTC_FAULT_TALLY)."""
    path = os.environ.get("FTC_FAULT_TALLY")
    if path:
        with open(path, "a") as f:
            f.write(json.dumps({"what": what, "n": n}) + "\n")


def run_cli(args: list[str], timeout: float = 60, cwd: Path | None = None):
    """The command's CompletedProcess; ``python -m`` tools are forked from a
    process that imported them once (tests/python/forked_tools.py)."""
    if args[:2] == [PY, "-m"]:
        return run_tool(args[2], args[3:], cwd=cwd or REPO, env=ENV, timeout=timeout)
    return subprocess.run(args, capture_output=True, text=True, timeout=timeout, env=ENV,
                          cwd=cwd or REPO)


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.strip()]


# ---------------------------------------------------------------------------
# Garbage on the plant's channels
# ---------------------------------------------------------------------------

def _command(seq: int, valves, num=None, session: int = 0) -> bytes:
    from ftc.valve_command_t import valve_command_t

    m = valve_command_t()
    m.session, m.seq, m.valve = session, seq, list(valves)
    m.num_valves = len(m.valve) if num is None else num
    return m.encode()


def _wait_for_counts(plant, decode_errors: int, rejected: int, deadline_s: float = 3.0):
    """HELLO until the plant's published counters reach the expected values."""
    deadline = time.monotonic() + deadline_s
    while True:
        plant.hello(timeout=1.0)
        s = plant.last_state
        if (s.decode_errors, s.rejected_commands) >= (decode_errors, rejected) \
                or time.monotonic() > deadline:
            return s


def _undecodable_messages(seq: int) -> dict[str, list[bytes]]:
    """Channel suffix -> messages the plant cannot decode on it."""
    from ftc.plant_control_t import plant_control_t
    from ftc.plant_state_t import plant_state_t

    state = plant_state_t()
    state.num_tanks, state.num_engines = 6, 2
    state.level = state.true_level = [0.5] * 6
    state.valve, state.deficit = [0] * 6, [0.0, 0.0]
    control = plant_control_t()
    control.seq, control.command = seq, plant_control_t.RESET
    good = _command(seq, [1] * 6)
    negative_count = bytearray(good)
    negative_count[40] = 0xFF  # num_valves = -1 (the fuzzer's first find)
    rng = random.Random(1)
    garbage = [bytes(rng.randrange(256) for _ in range(rng.randrange(0, 80)))
               for _ in range(40)]
    return {
        "COMMAND": [state.encode(), control.encode(), good[:-1], good + b"\0",
                    bytes(negative_count), bytes(negative_count[:41]), b"",
                    *[good[:n] for n in range(0, len(good), 3)], *garbage],
        "CONTROL": [good, state.encode(), control.encode()[:-1], control.encode() + b"x",
                    *garbage[:10]],
    }


def test_garbage_and_wrong_types_are_counted_and_the_plant_keeps_serving():
    import lcm

    with launch(None, 0) as plant:
        plant.reset()
        plant.step(np.ones(6))
        lc = lcm.LCM(plant.url)
        bad = _undecodable_messages(plant._seq + 1000)
        for suffix, messages in bad.items():
            for data in messages:
                lc.publish(plant.prefix + suffix, data)
        n = sum(len(v) for v in bad.values())
        s = _wait_for_counts(plant, n, 0)
        assert s.decode_errors == n  # exactly one count per undecodable message
        assert (s.rejected_commands, s.duplicate_commands, s.stale_commands) == (0, 0, 0)
        assert s.step == 1  # nothing stepped the plant
        o = plant.step(np.zeros(6))
        assert o.step == 2 and plant.process.poll() is None
        tally("undecodable messages published", n)


def test_out_of_range_commands_are_rejected_with_a_reason_and_counted():
    import lcm

    with launch(None, 0) as plant:
        plant.reset()
        lc = lcm.LCM(plant.url)
        base = plant._seq + 1000
        bad = [([0, 2, 0, 0, 0, 0], None, "valve[1] is 2, expected 0 or 1"),
               ([0, 0, 0, 0, 0, -1], None, "valve[5] is -1, expected 0 or 1"),
               ([127] * 6, None, "valve[0] is 127, expected 0 or 1"),
               ([1] * 5, None, "num_valves is 5, expected 6"),
               ([1] * 7, None, "num_valves is 7, expected 6"),
               ([], None, "num_valves is 0, expected 6")]
        for k, (valves, num, _) in enumerate(bad):
            lc.publish(plant.prefix + "COMMAND", _command(base + k, valves, num, plant.session))
        from ftc.plant_control_t import plant_control_t
        unknown = plant_control_t()
        unknown.session, unknown.seq, unknown.command = plant.session, base + len(bad), 9
        lc.publish(plant.prefix + "CONTROL", unknown.encode())
        # commands of the link's session it never sent (invalid ones too): another
        # sender holds the session id, and the link stops at its next answer
        # (ftc.plant.foreign), which carries the plant's counts
        from ftc.plant.link import ForeignTrafficError
        time.sleep(0.5)
        with pytest.raises(ForeignTrafficError, match="the plant rejected 7 commands of it"):
            plant.hello()
        s = plant.last_state
        assert s.rejected_commands == len(bad) + 1
        assert s.decode_errors == 0 and s.step == 0  # none applied
        log = Path(plant._stderr_path).read_text()
        for _, _, reason in bad:
            assert reason in log
        assert "unknown command 9" in log
        tally("out-of-range commands published", len(bad) + 1)


# ---------------------------------------------------------------------------
# Processes killed mid-run
# ---------------------------------------------------------------------------

def _children(pid: int) -> list[int]:
    try:
        text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    except OSError:
        return []
    return [int(c) for c in text.split()]


def _plant_child(pid: int, timeout: float = 10.0) -> int:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for c in _children(pid):
            try:
                if Path(f"/proc/{c}/exe").resolve() == plant_binary().resolve():
                    return c
            except OSError:
                pass
        time.sleep(0.05)
    raise AssertionError("the plant process did not start")


@pytest.mark.parametrize("after_s", [0.5, 1.5])
def test_plant_killed_under_simulate_gives_a_clear_error_and_no_csv(tmp_path, after_s):
    out = tmp_path / "traj.csv"
    proc = subprocess.Popen([PY, "-m", "ftc.simulate", "--steps", "1000000", "--policy", "random",
                             "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=ENV, cwd=REPO)
    try:
        plant = _plant_child(proc.pid)
        time.sleep(after_s)  # let it run mid-episode (the fault's timing, not synchronisation)
        os.kill(plant, signal.SIGKILL)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 1
    lines = error_lines(err)
    assert len(lines) == 1 and lines[0].startswith("ftc.simulate: error:")
    assert "exited with code -9" in lines[0]
    assert list(tmp_path.iterdir()) == []  # no CSV, no temporary file
    tally("plant killed under ftc.simulate", 1)


def test_plant_killed_mid_step_is_reported_as_gone_with_the_step(tmp_path):
    config = LinkConfig(retry_timeout=0.05, give_up_timeout=0.5)
    plant = launch(None, 0, config=config)
    try:
        plant.reset()
        for _ in range(7):
            plant.step(np.zeros(6))
        plant.process.send_signal(signal.SIGSTOP)  # hung, not dead: only the timeout tells
        start = time.monotonic()
        with pytest.raises(PlantGoneError, match=r"did not answer|gone"):
            plant.step(np.zeros(6))
        assert 0.4 < time.monotonic() - start < 1.5
        assert plant.retries >= 3  # re-sent with the same seq before giving up
    finally:
        plant.process.send_signal(signal.SIGCONT)
        plant.close()
    tally("plant hung (SIGSTOP)", 1)


_CONTROLLER = r"""
import sys, time, lcm
from ftc.plant_control_t import plant_control_t
from ftc.valve_command_t import valve_command_t
lc = lcm.LCM(sys.argv[1]); seq = 1
while True:
    if seq < 20:  # OPEN its session (seq 1) until the plant surely has it
        o = plant_control_t(); o.session, o.seq, o.command = 777, 1, plant_control_t.OPEN
        lc.publish(sys.argv[2] + "CONTROL", o.encode())
    m = valve_command_t(); seq += 1
    m.session, m.seq, m.num_valves, m.valve = 777, seq, 6, [1, 0, 1, 1, 0, 1]
    lc.publish(sys.argv[2] + "COMMAND", m.encode()); time.sleep(0.02)
"""


@pytest.mark.parametrize("safe_state,expected", [("closed", [0] * 6),
                                                  ("hold", [1, 0, 1, 1, 0, 1])])
def test_realtime_plant_reaches_its_safe_state_when_the_controller_is_killed(safe_state,
                                                                               expected):
    import lcm

    from ftc.plant_state_t import plant_state_t

    url, prefix, watchdog = private_lcm_url(), private_prefix(), 0.4
    plant = subprocess.Popen([str(plant_binary()), "--lcm-url", url, "--prefix", prefix,
                              "--mode", "realtime", "--rate", "50", "--watchdog", str(watchdog),
                              "--safe-state", safe_state], stderr=subprocess.DEVNULL)
    controller = subprocess.Popen([PY, "-c", _CONTROLLER, url, prefix], env=ENV)
    try:
        lc = lcm.LCM(url)
        states: list[tuple[float, object]] = []
        lc.subscribe(prefix + "STATE",
                     lambda c, d: states.append((time.monotonic(), plant_state_t.decode(d))))

        def pump_until(pred, seconds):
            deadline = time.monotonic() + seconds
            while time.monotonic() < deadline:
                lc.handle_timeout(20)
                if states and pred(states[-1][1]):
                    return True
            return False

        assert pump_until(lambda s: not s.watchdog_tripped and list(s.valve) == expected
                          if safe_state == "hold" else not s.watchdog_tripped, 10.0)
        controlled = states[-1][1]
        assert list(controlled.valve) == [1, 0, 1, 1, 0, 1]
        controller.kill()
        controller.wait()
        killed = time.monotonic()
        assert pump_until(lambda s: s.watchdog_tripped, watchdog + 1.0)
        tripped_at, tripped = states[-1]
        # within the watchdog time plus two ticks (20 ms each) and delivery
        assert tripped_at - killed <= watchdog + 0.15
        pump_until(lambda s: False, 0.2)
        after = [s for t, s in states if t > tripped_at + 0.05]
        assert after and all(s.watchdog_tripped for s in after)
        # the valves applied on each step; an episode's first state (step 0,
        # the plant reset on that tick) has applied none and reports them closed
        assert all(list(s.valve) == expected for s in after if s.step > 0), \
            [(s.step, list(s.valve)) for s in after]
        assert plant.poll() is None
    finally:
        if controller.poll() is None:
            controller.kill()
        plant.send_signal(signal.SIGINT)
        assert plant.wait(timeout=5) == 0
    tally("controller killed under a real-time plant", 1)


# ---------------------------------------------------------------------------
# LCM logs: truncated and corrupted
# ---------------------------------------------------------------------------

def _write_log(path: Path, prefix: str = "FTC_", steps: int = 30,
               bad_payload=None) -> None:
    import lcm

    from ftc.plant_state_t import plant_state_t

    log = lcm.EventLog(str(path), "w", overwrite=True)
    for k in range(steps + 1):
        s = plant_state_t()
        s.seq, s.command_seq, s.episode, s.step = k + 1, k, 0, k
        s.num_tanks, s.num_engines = 6, 2
        s.level = s.true_level = [1.0 - 0.01 * k] * 6
        s.valve, s.deficit = [0] * 6, [0.0, 0.0]
        s.terminal = k == steps
        data = s.encode()
        if bad_payload is not None and k == steps // 2:
            data = bad_payload(data)
        log.write_event(1000 * k, prefix + "STATE", data)
    log.close()


def _log_faults(good: bytes) -> dict[str, bytes]:
    rng = random.Random(5)
    faults = {f"truncated at {n}": good[:n] for n in (1, 4, 10, 27)}
    faults["truncated at half"] = good[:len(good) // 2]
    faults["truncated one byte short"] = good[:-1]
    sync = good.find(b"\xed\xa1\xda\x01", len(good) // 3)  # an event's sync word
    faults["sync word corrupted"] = good[:sync] + b"\x00\x00\x00\x00" + good[sync + 4:]
    # (a flipped byte inside a message's levels cannot be detected: LCM logs
    # carry no checksum; only framing and decoding errors can be)
    faults["garbage appended"] = good + b"\x01garbage"
    faults["garbage only"] = bytes(rng.randrange(256) for _ in range(300))
    middle = bytearray(good)
    # the first event's data length field (after the 4-byte sync, 8-byte number,
    # 8-byte timestamp and 4-byte channel length) set far past the end
    middle[24:28] = (10 ** 8).to_bytes(4, "big")
    faults["event length past the end"] = bytes(middle)
    return faults


def _event_starts(path: Path) -> list[int]:
    import lcm

    log = lcm.EventLog(str(path), "r")
    starts = [log.tell()]
    while log.read_next_event() is not None:
        starts.append(log.tell())
    log.close()
    return starts[:-1]


def _expected_stop(good: Path, data: bytes) -> tuple[int, int]:
    """(byte offset, events read) where reading a damaged copy of ``good`` must
    stop: at the start of the last event that begins before the first damaged
    byte. (liblcm checks the header that follows an event, so the intact event
    just before a damaged header is not read either.)"""
    original = good.read_bytes()
    damaged = next((i for i, (a, b) in enumerate(zip(original, data)) if a != b),
                   min(len(original), len(data)))
    starts = _event_starts(good)
    before = [s for s in starts if s < damaged] or [0]
    return before[-1], len(before) - 1 if damaged else 0


def test_replay_of_a_good_log_works(tmp_path):
    log = tmp_path / "good.lcmlog"
    _write_log(log)
    out = run_cli([PY, "-m", "ftc.replay", str(log)])
    assert out.returncode == 0, out.stderr


@pytest.mark.parametrize("fault", list(_log_faults(b"x" * 2000)))
def test_replay_of_a_truncated_or_corrupt_log_exits_2_naming_file_and_offset(tmp_path, fault):
    good = tmp_path / "good.lcmlog"
    _write_log(good)
    bad = tmp_path / "bad.lcmlog"
    bad.write_bytes(_log_faults(good.read_bytes())[fault])
    csv = tmp_path / "traj.csv"
    out = run_cli([PY, "-m", "ftc.replay", str(bad), "--csv", str(csv)])
    assert out.returncode == 2, (fault, out.stdout, out.stderr)
    lines = error_lines(out.stderr)
    assert len(lines) == 1, lines
    data = bad.read_bytes()
    stop = _expected_stop(good, data)
    m = re.fullmatch(rf"ftc\.replay: error: {re.escape(str(bad))}: truncated or corrupt log: "
                     rf"reading stopped at byte offset (\d+) of {len(data)} \(after (\d+) "
                     r"events\)( \(lcm: .+\))?", lines[0])
    assert m, lines[0]
    assert (int(m[1]), int(m[2])) == stop, (fault, lines[0], stop)
    assert not csv.exists()
    tally("corrupt LCM logs to ftc.replay", 1)


@pytest.mark.parametrize("payload", ["truncated", "extended", "wrong type", "garbage",
                                     "negative count"])
def test_replay_skips_and_names_a_well_framed_message_that_is_no_plant_state(tmp_path, payload):
    from ftc.valve_command_t import valve_command_t

    def negative(d: bytes) -> bytes:  # num_tanks = -1 (after fingerprint and 56 bytes of fields)
        return d[:64] + b"\xff" + d[65:]

    change = {"truncated": lambda d: d[:-5], "extended": lambda d: d + b"\0" * 3,
              "wrong type": lambda d: valve_command_t().encode(),
              "garbage": lambda d: b"\x07" * len(d), "negative count": negative}[payload]
    log = tmp_path / "bad.lcmlog"
    _write_log(log, bad_payload=change)
    out = run_cli([PY, "-m", "ftc.replay", str(log)])
    # another process's traffic on the bus, recorded as it was: not the log's fault
    assert out.returncode == 0, (payload, out.stdout, out.stderr)
    warning = [line for line in out.stdout.splitlines() if line.startswith("WARNING: 1 messages")]
    assert len(warning) == 1 and "event 15 at byte offset" in warning[0], out.stdout
    assert "29 plant steps" in out.stdout  # the 30 good steps but the skipped one
    tally("well-framed logs with a bad message", 1)


def test_replay_of_a_missing_or_empty_log_exits_2(tmp_path):
    for path in (tmp_path / "missing.lcmlog", tmp_path / "empty.lcmlog"):
        if path.name.startswith("empty"):
            path.write_bytes(b"")
        out = run_cli([PY, "-m", "ftc.replay", str(path)])
        assert out.returncode == 2, out.stderr
        lines = error_lines(out.stderr)
        assert len(lines) == 1 and str(path) in lines[0], lines
    tally("missing/empty LCM logs to ftc.replay", 2)


# ---------------------------------------------------------------------------
# Malformed scenario files
# ---------------------------------------------------------------------------

def _expected_key(bad: Path) -> str:
    """The key a bad_*.toml is about: its first assignment's key."""
    for line in bad.read_text().splitlines():
        line = line.strip()
        if line.startswith("[") and "]" in line:
            table = line.strip("[]").strip()
            continue
        if "=" in line and not line.startswith("#"):
            key = line.split("=")[0].strip()
            if key != "name":
                return key
    raise AssertionError(bad)


def _assert_scenario_error(out, bad: Path, tool: str) -> None:
    assert out.returncode == 2, (tool, bad.name, out.stderr)
    lines = error_lines(out.stderr)
    assert len(lines) == 1, (tool, bad.name, lines)
    assert str(bad) in lines[0], (tool, lines[0])
    assert _expected_key(bad) in lines[0], (tool, bad.name, lines[0])


@pytest.mark.parametrize("bad", BAD_SCENARIOS, ids=lambda p: p.name)
def test_malformed_scenario_to_plant_simulate_and_mpc_exits_2_writes_nothing(tmp_path, bad):
    _assert_scenario_error(run_cli([str(plant_binary()), "--scenario", str(bad)], timeout=10),
                           bad, "plant")
    out_csv = tmp_path / "sim" / "traj.csv"
    _assert_scenario_error(run_cli([PY, "-m", "ftc.simulate", "--scenario", str(bad),
                                    "--out", str(out_csv)]), bad, "ftc.simulate")
    assert list(tmp_path.iterdir()) == [], list(tmp_path.rglob("*"))
    tally("malformed scenario files (plant, ftc.simulate)", 2)


@pytest.mark.parametrize("bad", BAD_SCENARIOS, ids=lambda p: p.name)
def test_malformed_scenario_to_mpc_exits_2_writes_nothing(tmp_path, bad):
    mpc_out = tmp_path / "mpc"
    tally("malformed scenario files (ftc.mpc)", 1)
    _assert_scenario_error(run_cli([PY, "-m", "ftc.mpc", "--scenario", str(bad), "--out",
                                    str(mpc_out), "--intervals", "1", "--steps-per-interval",
                                    "8"], cwd=tmp_path), bad, "ftc.mpc")
    assert list(tmp_path.iterdir()) == [], list(tmp_path.rglob("*"))


# ---------------------------------------------------------------------------
# Bad flags
# ---------------------------------------------------------------------------

_SCEN = str(REPO / "scenarios" / "single.toml")
BAD_FLAGS = {
    "plant": [([], "--no-such-flag", ["--no-such-flag"]),
              ([], "--rate", ["--rate", "0"]),
              ([], "--rate", ["--rate", "fast"]),
              ([], "--watchdog", ["--watchdog", "-1"]),
              ([], "--mode", ["--mode", "sometimes"]),
              ([], "--safe-state", ["--safe-state", "open"]),
              ([], "--seed", ["--seed", "-3x"]),
              ([], "--steps-per-interval", ["--steps-per-interval", "0"]),
              ([], "--start-step", ["--start-step", "-1"]),
              ([], "--scenario", ["--scenario", "/no/such/file.toml"])],
    "ftc.simulate": [(["--out", "x.csv"], "--no-such-flag", ["--no-such-flag"]),
                     (["--out", "x.csv"], "--steps", ["--steps", "0"]),
                     (["--out", "x.csv"], "--steps", ["--steps", "ten"]),
                     (["--out", "x.csv"], "--policy", ["--policy", "greedy"]),
                     (["--out", "x.csv"], "--seed", ["--seed", "1.5"]),
                     (["--out", "x.csv"], "--scenario", ["--scenario", "/no/such.toml"]),
                     (["--out", "x.csv"], "--steps-per-interval",
                      ["--steps-per-interval", "0"]),
                     ([], "--out", [])],
    "ftc.experiments": [(["single"], "--no-such-flag", ["--no-such-flag"]),
                        (["single"], "--jobs", ["--jobs", "many"]),
                        (["single"], "--intervals", ["--intervals", "0"]),
                        (["single"], "--steps-per-interval", ["--steps-per-interval", "-5"]),
                        (["single"], "--trials", ["--trials", "0"]),
                        (["single"], "--methods", ["--methods", "telepathy"]),
                        ([], "command", ["everything"]),
                        (["report"], "--out", ["--out", "/no/such/run"])],
    "ftc.replay": [(["x.lcmlog"], "--no-such-flag", ["--no-such-flag"]),
                   (["x.lcmlog"], "--episode", ["--episode", "last"]),
                   ([], "log", [])],
    "ftc.mpc": [([], "--no-such-flag", ["--no-such-flag"]),
                ([], "--method", ["--method", "psychic"]),
                ([], "--planner", ["--planner", "none"]),
                ([], "--horizon", ["--horizon", "0"]),
                ([], "--intervals", ["--intervals", "0"]),
                ([], "--steps-per-interval", ["--steps-per-interval", "0"]),
                ([], "--scenario", ["--scenario", "/no/such.toml"]),
                ([], "--cem-samples", ["--cem-samples", "x"]),
                ([], "--lcm-url", ["--lcm-url", "udpm://239.255.76.67:7667?ttl=1"])],
    "ftc.relay": [(["--client-prefix", "A_", "--plant-prefix", "B_"], "--no-such-flag",
                   ["--no-such-flag"]),
                  (["--client-prefix", "A_", "--plant-prefix", "B_"], "--loss", ["--loss", "1"]),
                  (["--client-prefix", "A_", "--plant-prefix", "B_"], "--loss",
                   ["--loss", "-0.1"]),
                  (["--client-prefix", "A_", "--plant-prefix", "B_"], "--duplicate",
                   ["--duplicate", "nan"]),
                  (["--client-prefix", "A_", "--plant-prefix", "B_"], "--lcm-url",
                   ["--lcm-url", "udpm://239.255.76.67:7667?ttl=1"]),
                  (["--client-prefix", "A_"], "--plant-prefix", []),
                  (["--client-prefix", "A_", "--plant-prefix", "A_"], "prefix", [])],
}
_CASES = [pytest.param(tool, base, flag, args,
                       id=f"{tool}{' '.join(args) or '-missing-' + flag}")
          for tool, cases in BAD_FLAGS.items() for base, flag, args in cases]


@pytest.mark.parametrize("tool,base,flag,args", _CASES)
def test_bad_flag_exits_2_naming_the_flag_and_writes_nothing(tmp_path, tool, base, flag, args):
    tally("bad CLI flags", 1)
    cmd = [str(plant_binary())] if tool == "plant" else [PY, "-m", tool]
    out = run_cli(cmd + base + args, timeout=30, cwd=tmp_path)
    assert out.returncode == 2, (out.stdout, out.stderr)
    assert flag.lstrip("-") in out.stderr, out.stderr
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("tool", ["ftc.mpc", "ftc.controller"])
def test_a_fresh_tool_process_refuses_a_bad_flag_and_writes_nothing(tmp_path, tool):
    # the cases above fork the tools from a process that imported them elsewhere:
    # one fresh `python -m` each, so that import-time writes or environment reads
    # in the working directory would still show
    out = subprocess.run([PY, "-m", tool, "--no-such-flag"], capture_output=True, text=True,
                         timeout=60, env=ENV, cwd=tmp_path)
    assert out.returncode == 2 and "no-such-flag" in out.stderr, (out.stdout, out.stderr)
    assert list(tmp_path.iterdir()) == []


# ---------------------------------------------------------------------------
# Unwritable output
# ---------------------------------------------------------------------------

def _unwritable(tmp_path: Path) -> Path:
    # A path below a regular file: unwritable even for root.
    blocker = tmp_path / "blocker"
    blocker.write_text("not a directory\n")
    return blocker / "out"


def test_simulate_unwritable_out_fails_before_starting_the_plant(tmp_path):
    out_dir = _unwritable(tmp_path)
    start = time.monotonic()
    out = run_cli([PY, "-m", "ftc.simulate", "--steps", "100000", "--out",
                   str(out_dir / "traj.csv")])
    assert out.returncode == 2, out.stderr
    lines = error_lines(out.stderr)
    assert "--out" in lines[-1] and str(out_dir) in lines[-1]
    assert time.monotonic() - start < 10  # 100000 steps would take far longer
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blocker"]
    tally("unwritable --out", 1)


def test_experiments_unwritable_out_fails_before_any_run(tmp_path):
    out_dir = _unwritable(tmp_path)
    out = run_cli([PY, "-m", "ftc.experiments", "single", "--out", str(out_dir),
                   "--intervals", "1", "--steps-per-interval", "8", "--methods", "closed"])
    assert out.returncode == 2, out.stderr
    lines = error_lines(out.stderr)
    assert "--out" in lines[-1] and str(out_dir) in lines[-1], lines
    assert sorted(p.name for p in tmp_path.iterdir()) == ["blocker"]
    tally("unwritable --out", 1)


# ---------------------------------------------------------------------------
# Security
# ---------------------------------------------------------------------------

NETWORK_URLS = ["udpm://239.255.76.67:7667?ttl=1", "udpm://239.255.76.67:7667",
                "udpm://239.255.76.67:7667?ttl=0&ttl=1", "tcpq://10.0.0.1:7700",
                "udpm://239.255.76.67:7667?ttl=10"]


@pytest.mark.parametrize("url", NETWORK_URLS)
def test_network_lcm_urls_are_refused_unless_allowed(url):
    with pytest.raises(ValueError, match="may leave this machine"):
        check_loopback_url(url)
    with pytest.warns(UserWarning, match="may leave this machine"):
        check_loopback_url(url, allow_network=True)
    out = run_cli([str(plant_binary()), "--lcm-url", url], timeout=10)
    assert out.returncode == 2 and "ttl=0" in out.stderr and "--allow-network" in out.stderr
    tally("network LCM URLs", 2)


def test_loopback_urls_are_accepted():
    for url in ("udpm://239.255.76.67:7667?ttl=0", "memq://"):
        check_loopback_url(url)


def test_nothing_is_unpickled():
    sources = sorted((REPO / "python" / "ftc").rglob("*.py"))
    assert len(sources) > 40  # every room, not only the top-level shims
    for path in sources:
        text = path.read_text()
        assert not re.search(r"^\s*(import|from)\s+(c?pickle|dill|joblib|shelve)\b", text,
                             re.M), path
        assert "pickle.load" not in text, path
        for call in re.finditer(r"torch\.load\(", text):
            depth, end = 1, call.end()
            while depth and end < len(text):
                depth += {"(": 1, ")": -1}.get(text[end], 0)
                end += 1
            assert "weights_only=True" in text[call.end():end], \
                f"{path.name}: torch.load without weights_only=True"
        assert "allow_pickle=True" not in text, path
