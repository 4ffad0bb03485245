"""The bus against a hostile or careless neighbour (issue: no message from a
neighbour can crash a node, corrupt a run or take the valves), with the real
plant, policy node and lcm_echo processes on a private loopback port:

* malformed messages (hostile array lengths, truncations, random bytes) are
  counted and survived, and a process's memory stays bounded;
* sessions: commands, START, RESET and SHUTDOWN of another session change
  nothing (a lockstep run stays identical to an undisturbed one) and are
  counted by the plant; forged states cannot stop or poison a receiver.
"""

from __future__ import annotations

import random
import re
import struct
import subprocess
import time
from pathlib import Path

import lcm
import numpy as np
import pytest

from ftc.common.build_info import plant_binary, policy_node_binary
from ftc.plant import launch, private_lcm_url, private_prefix
from ftc.plant.realtime_link import RealtimeLink
from ftc.plant.wire import check_state, decode_state
from ftc.plant_control_t import plant_control_t
from ftc.plant_state_t import plant_state_t
from ftc.policy_t import policy_t
from ftc.tools import policy_weights as pw
from ftc.valve_command_t import valve_command_t

REPO = Path(__file__).resolve().parents[2]
# Peak resident memory a node may reach under the hostile messages below
# (measured 6.9 MB for the policy node; a 250M-param push used to take 982 MB).
NODE_RSS_BOUND_MB = 64


def _state(session: int = 0, seq: int = 1, tanks: int = 6) -> bytes:
    s = plant_state_t()
    s.session, s.seq, s.num_tanks, s.num_engines = session, seq, tanks, 2
    s.level, s.true_level = [0.5] * tanks, [0.5] * tanks
    s.valve, s.deficit = [1] * tanks, [0.0, 0.0]
    return s.encode()


def _policy_header(num_widths: int, num_params: int | None, size: int) -> bytes:
    """A policy_t of `size` bytes declaring these counts (the rest zeros)."""
    data = policy_t._get_packed_fingerprint() + struct.pack(">qqi", 0, 2, num_widths)
    if num_params is not None:
        data += struct.pack(">i", num_params)
    return (data + bytes(size))[:size]


def hostile_messages() -> dict[str, list[bytes]]:
    """Channel suffix -> the issue's crashing messages and more garbage."""
    negative_tanks = bytearray(_state())
    negative_tanks[8 + 8 * 4 + 4 + 4 + 8 + 8] = 0xFF  # num_tanks = -1
    rng = random.Random(7)
    garbage = [bytes(rng.randrange(256) for _ in range(rng.randrange(0, 120)))
               for _ in range(20)]
    good_state = _state()
    return {
        "STATE": [bytes(negative_tanks), good_state[:-3], good_state + b"\0", *garbage],
        # (no more than the node queues, 8: LCM drops a burst beyond that)
        "POLICY": [_policy_header(-1, None, 64),                # std::length_error
                   _policy_header(0x20000001, None, 36),        # int overflow, SIGSEGV
                   _policy_header(0, 250_000_000, 40),          # 1 GB allocation
                   *garbage[:5]],
    }


def _peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmHWM")


def _logged_state(k: int) -> plant_state_t:
    """Step k of a recorded run of the plant: 6 tanks draining 0.01 a step."""
    s = plant_state_t()
    s.seq, s.step, s.num_tanks, s.num_engines = k + 1, k, 6, 2
    s.level = s.true_level = [1.0 - 0.01 * k] * 6
    s.valve, s.deficit = [0] * 6, [0.0, 0.0]
    return s


def test_python_state_check_refuses_what_would_crash_a_decoder():
    assert check_state(_state()) is None
    bad = bytearray(_state())
    bad[8 + 8 * 4 + 4 + 4 + 8 + 8] = 0xFF
    assert "num_tanks -1" in check_state(bytes(bad))
    assert "fingerprint" in check_state(_policy_header(0, 0, 40))
    assert "bytes where" in check_state(_state()[:-1])
    assert check_state(b"") is not None
    # well formed but not this plant's shape: refused by decode_state
    assert check_state(_state(tanks=3)) is None
    assert decode_state(_state(tanks=3)) == (None, "num_tanks 3, num_engines 2 (this plant has "
                                                   "6 and 2)")
    assert decode_state(_state())[0].num_tanks == 6


def test_replay_skips_a_state_of_another_shape(tmp_path):
    """A neighbour's well-formed state of 3 tanks on the recorded STATE channel:
    ftc.replay ended in a traceback (exit 1, in read_log); it is skipped and
    named (ftc.replay's summary prints the first such message)."""
    from ftc.plant.log import read_log

    path = tmp_path / "shapes.lcmlog"
    log = lcm.EventLog(str(path), "w", overwrite=True)
    for k in range(11):
        log.write_event(1000 * k, "RUN_STATE", _logged_state(k).encode())
    other = plant_state_t.decode(_state(0, 12, tanks=3))
    other.step = 11  # the step after the last: a new row, of 3 levels
    log.write_event(20_000, "RUN_STATE", other.encode())
    log.close()
    traj = read_log(path)
    assert len(traj) == 10 and traj.undecodable == 1
    assert "num_tanks 3, num_engines 2" in traj.first_undecodable


def test_the_policy_node_survives_hostile_messages_with_bounded_memory(tmp_path, scenarios):
    url, prefix = private_lcm_url(), private_prefix()
    path = tmp_path / "p.txt"
    pw.write_weights(path, [6, 6], np.zeros(42, np.float32), version=1)
    plant = subprocess.Popen([str(plant_binary()), "--scenario", str(scenarios / "single.toml"),
                              "--mode", "realtime", "--rate", "50", "--lcm-url", url,
                              "--prefix", prefix], stderr=subprocess.DEVNULL)
    node = subprocess.Popen([str(policy_node_binary()), "--policy", str(path), "--lcm-url", url,
                             "--prefix", prefix, "--steps", "120"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    lc = lcm.LCM(url)
    commands: list = []
    lc.subscribe(prefix + "COMMAND",
                 lambda _c, d: commands.append(valve_command_t.decode(d)))
    try:
        deadline = time.monotonic() + 20
        while len(commands) < 10:
            assert time.monotonic() < deadline, "no commands from the node"
            lc.handle_timeout(50)
        session = commands[-1].session
        sent = hostile_messages()
        for suffix, messages in sent.items():
            for data in messages:
                lc.publish(prefix + suffix, data)
        # forged states in the node's own session: far ahead (would stop it for
        # good) and far behind (would look like a restart)
        lc.publish(prefix + "STATE", _state(session, 2**62))
        lc.publish(prefix + "STATE", _state(session, 1))
        lc.publish(prefix + "STATE", _state(session + 1, 10**9))  # another session
        time.sleep(0.3)
        assert node.poll() is None, node.communicate()
        peak = _peak_rss_mb(node.pid)
        out, err = node.communicate(timeout=30)
    finally:
        node.kill()
        plant.kill()
        plant.wait()
    assert node.returncode == 0, err
    assert re.match(r"^steps 120 deadline_misses \d+ ", out.strip()), out
    bad = sum(len(v) for v in sent.values())
    counts = re.search(r"refused messages: bad decode (\d+), other session (\d+), stale (\d+), "
                       r"seq jump (\d+)", err)
    assert counts, err
    # every hostile buffer counted; the forged states too (the other session's
    # count also holds the plant's states before the node's session opened)
    assert int(counts.group(1)) == bad
    assert int(counts.group(2)) >= 1 and int(counts.group(3)) >= 1
    assert int(counts.group(4)) == 1
    assert peak < NODE_RSS_BOUND_MB, f"peak RSS {peak:.0f} MB"


def test_lcm_echo_survives_a_negative_valve_count():
    from ftc.common.build_info import echo_binary

    url, prefix = private_lcm_url(), private_prefix()
    echo = subprocess.Popen([str(echo_binary()), "--lcm-url", url, "--prefix", prefix],
                            stderr=subprocess.PIPE, text=True)
    lc = lcm.LCM(url)
    answers: list = []
    lc.subscribe(prefix + "STATE", lambda _c, d: answers.append(plant_state_t.decode(d)))
    try:
        cmd = valve_command_t()
        cmd.seq, cmd.num_valves, cmd.valve = 5, 6, [0] * 6
        bad = bytearray(cmd.encode())
        bad[8 + 8 * 4] = 0xFF  # num_valves = -1: lcm_echo aborted (exit 134)
        deadline = time.monotonic() + 10
        while not answers:  # until the echo is up and answers the valid command
            assert time.monotonic() < deadline and echo.poll() is None
            lc.publish(prefix + "COMMAND", bytes(bad))
            lc.publish(prefix + "COMMAND", cmd.encode())
            lc.handle_timeout(100)
        assert answers[0].command_seq == 5 and echo.poll() is None
        # the echo may have come up between the two publishes and never heard the bad
        # one: now that it listens, the bad command, then a valid one it answers only
        # after it (one sender on loopback: in order)
        cmd.seq = 6
        while not any(a.command_seq == 6 for a in answers):
            assert time.monotonic() < deadline and echo.poll() is None
            lc.publish(prefix + "COMMAND", bytes(bad))
            lc.publish(prefix + "COMMAND", cmd.encode())
            lc.handle_timeout(100)
        assert echo.poll() is None
    finally:
        echo.terminate()
        _, err = echo.communicate(timeout=5)
    assert echo.returncode == 0
    assert "num_valves is -1" in err


def test_lcm_echo_moves_its_counters_as_the_plant_does():
    """The lockstep benchmark's floor (scripts/bench.py) runs a lockstep link
    against lcm_echo. The link stops at any answer that does not follow from
    its own request (ftc.plant.foreign), so the echo's episode, step, operating
    step and valves must move as the plant's do, or the benchmark stops with
    'foreign traffic' on its first reset."""
    from ftc.common.build_info import echo_binary
    from ftc.plant import LcmPlant

    url, prefix = private_lcm_url(), private_prefix()
    proc = subprocess.Popen([str(echo_binary()), "--lcm-url", url, "--prefix", prefix])
    rng = np.random.default_rng(0)
    with LcmPlant(url, prefix, process=proc) as echo:
        o = echo.reset()
        first = o.episode
        for k in range(1, 41):
            valves = rng.integers(0, 2, 6)
            o = echo.step(valves)
            assert (o.step, list(o.valves)) == (k, list(valves))
        assert o.operating_steps == 40
        o = echo.evaluate()
        o = echo.step(np.ones(6, dtype=np.int8))
        assert (o.episode, o.step, o.operating_steps) == (first + 1, 1, 40)  # evaluation: no age
        o = echo.reset()
        assert (o.episode, o.step) == (first + 2, 0)


def test_lcm_echo_with_a_key_answers_only_signed_messages_and_signs_its_answers(tmp_path):
    from ftc.common.build_info import echo_binary
    from ftc.plant.signing import Auth, new_key

    url, prefix = private_lcm_url(), private_prefix()
    key = new_key()
    key_file = tmp_path / "bus.key"
    key_file.write_text(key.hex())
    key_file.chmod(0o600)
    echo = subprocess.Popen([str(echo_binary()), "--lcm-url", url, "--prefix", prefix,
                             "--key-file", str(key_file)], stderr=subprocess.PIPE, text=True)
    lc, auth = lcm.LCM(url), Auth(key)
    answers: list = []

    def on_state(channel, data):
        payload, cause = Auth(key).verify(channel, data)  # a fresh receiver: no replay state
        answers.append(plant_state_t.decode(payload) if payload is not None else cause)

    lc.subscribe(prefix + "STATE", on_state)

    def command(seq: int) -> bytes:
        cmd = valve_command_t()
        cmd.session, cmd.seq, cmd.num_valves, cmd.valve = 7, seq, 6, [0] * 6
        return cmd.encode()

    try:
        deadline = time.monotonic() + 10
        while not answers:  # until the echo is up: a signed command is answered, signed
            assert time.monotonic() < deadline and echo.poll() is None
            lc.publish(prefix + "COMMAND", auth.sign(prefix + "COMMAND", command(1)))
            lc.handle_timeout(100)
        signed = auth.sign(prefix + "COMMAND", command(2))
        for data in (command(3), signed, signed):  # unsigned, then signed, then replayed
            lc.publish(prefix + "COMMAND", data)
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            lc.handle_timeout(50)
    finally:
        echo.terminate()
        _, err = echo.communicate(timeout=5)
    assert echo.returncode == 0
    assert all(not isinstance(a, str) for a in answers)  # every answer verifies
    assert 2 in [a.command_seq for a in answers] and 3 not in [a.command_seq for a in answers]
    # the first signed command may have been sent before the echo listened: the
    # unsigned one and the replay are the refusals
    assert "bad signature 1, replay 1," in err, err


def _foreign(lc, prefix: str, plant) -> int:
    """A neighbour's traffic in another session: commands with the seq a
    clock-based controller would use, START at INT64_MAX, RESET, SHUTDOWN,
    CLOSE. Returns the number of messages sent."""
    n = 0
    for k in range(3):
        cmd = valve_command_t()
        cmd.session, cmd.seq = plant.session ^ 1, time.time_ns() // 1000 + k
        cmd.num_valves, cmd.valve = 6, [1, 0, 1, 0, 1, 0]
        lc.publish(plant.prefix + "COMMAND", cmd.encode())
        n += 1
    for command, step in ((plant_control_t.START, 2**63 - 1), (plant_control_t.RESET, 0),
                          (plant_control_t.SHUTDOWN, 0), (plant_control_t.CLOSE, 0),
                          (plant_control_t.OPEN, 0)):
        for session in (0, 12345):
            msg = plant_control_t()
            msg.session, msg.seq, msg.command, msg.operating_step = session, 10**15, command, step
            lc.publish(plant.prefix + "CONTROL", msg.encode())
            n += 1
    return n


def _run(scenarios, disturb: bool) -> tuple[list, int]:
    with launch(scenarios / "single.toml", 3, extra_args=["--steps-per-interval", "40"]) as plant:
        lc = lcm.LCM(plant.url)
        obs, sent = [plant.reset()], 0
        rng = np.random.default_rng(0)
        for t in range(30):
            if disturb and t % 10 == 5:
                sent += _foreign(lc, plant.prefix, plant)
            obs.append(plant.step(rng.integers(0, 2, 6)))
        plant.hello()
        refused = int(plant.last_state.other_session)
        assert plant.process.poll() is None  # no SHUTDOWN obeyed
    assert refused == sent
    return obs, sent


def test_foreign_sessions_change_nothing_in_a_lockstep_run(scenarios):
    undisturbed, _ = _run(scenarios, False)
    disturbed, sent = _run(scenarios, True)
    assert sent == 3 * 13
    for a, b in zip(undisturbed, disturbed, strict=True):
        assert np.array_equal(a.true_level, b.true_level) and a.step == b.step
        assert a.operating_steps == b.operating_steps


def _command(session: int, seq: int, valves=(1, 1, 1, 1, 1, 1)) -> bytes:
    cmd = valve_command_t()
    cmd.session, cmd.seq, cmd.num_valves, cmd.valve = session, seq, 6, list(valves)
    return cmd.encode()


def _control(session: int, seq: int, command: int) -> bytes:
    msg = plant_control_t()
    msg.session, msg.seq, msg.command = session, seq, command
    return msg.encode()


@pytest.mark.parametrize("attack", ["races the next seq", "runs ahead"])
def test_without_a_key_a_same_session_sniffer_stops_a_lockstep_run_in_one_line(scenarios,
                                                                                attack):
    """A neighbour without a key that read the session off the bus (every state
    carries it) sends a command in it: with the controller's next seq, before the
    controller (the plant applies the first and rejects the second as a repeat
    with other valves), or a seq ahead (the controller's become stale). The link
    stops at its next request with one line naming foreign traffic, never going on
    from a state it did not drive."""
    from ftc.plant.link import ForeignTrafficError

    with launch(scenarios / "single.toml", 3, extra_args=["--steps-per-interval", "40"]) as plant:
        lc = lcm.LCM(plant.url)
        plant.reset()
        for _ in range(3):
            plant.step([0] * 6)
        ahead = 1 if attack == "races the next seq" else 5
        lc.publish(plant.prefix + "COMMAND", _command(plant.session, plant._seq + ahead))
        time.sleep(0.05)  # the neighbour's command is first at the plant
        steps = 0
        with pytest.raises(ForeignTrafficError) as e:
            for _ in range(3):
                plant.step([0] * 6)
                steps += 1
        assert steps == (1 if ahead == 1 else 0)  # the raced step was taken, no more
    message = str(e.value)
    assert "\n" not in message and message.startswith("foreign traffic in this run's control session")
    assert ("repeat" in message) if ahead == 1 else ("never sent" in message), message


def test_a_takeover_after_the_session_timeout_stops_a_lockstep_run_in_one_line(scenarios):
    """The controller idles past the plant's --session-timeout; a neighbour opens a
    session of its own, steps the plant, closes, and reopens the controller's
    session (read off the bus): the controller's next step is applied, but its
    answer does not follow from the last one by that step: the run stops."""
    from ftc.plant.link import ForeignTrafficError

    with launch(scenarios / "single.toml", 3, extra_args=[
            "--steps-per-interval", "40", "--session-timeout", "0.2"]) as plant:
        lc = lcm.LCM(plant.url)
        plant.reset()
        plant.step([0] * 6)
        time.sleep(0.4)  # idle past the session timeout
        mine = 4242
        sent = [_control(mine, 1, plant_control_t.OPEN), _command(mine, 2), _command(mine, 3),
                _control(mine, 4, plant_control_t.CLOSE),
                _control(plant.session, 1, plant_control_t.OPEN)]
        for data in sent:
            lc.publish(plant.prefix + ("COMMAND" if data in sent[1:3] else "CONTROL"), data)
            time.sleep(0.02)
        with pytest.raises(ForeignTrafficError) as e:
            plant.step([0] * 6)
    message = str(e.value)
    assert "\n" not in message and "after its step the plant is at episode" in message, message


def test_forged_states_neither_stop_nor_poison_a_realtime_controller():
    link = launch(None, 0, extra_args=["--mode", "realtime", "--rate", "50"],
                  link_class=RealtimeLink)
    try:
        link.control(link.START, 0)
        lc = lcm.LCM(link.url)
        states = link.next_states()
        last = states[-1].seq
        for seq in (2**62, 1, last):  # far ahead, behind, a repeat
            lc.publish(link.prefix + "STATE", _state(link.session, seq))
        lc.publish(link.prefix + "STATE", _state(0, last + 1))  # another session
        lc.publish(link.prefix + "STATE", b"\x00" * 40)
        # well formed, the session's next seq, but 3 tanks: no state of this plant
        lc.publish(link.prefix + "STATE", _state(link.session, last + 1, tanks=3))
        got = []
        while len(got) < 10:
            got += link.next_states()
        seqs = [s.seq for s in got]
        assert seqs == list(range(last + 1, last + 1 + len(seqs)))  # the plant's, in order
        assert link.refused == {"bad decode": 2, "other session": 1, "stale": 2, "seq jump": 1,
                                "bad signature": 0, "replay": 0, "old timestamp": 0}
    finally:
        link.close()


def _run_session_state(lc, states: list, run: subprocess.Popen):
    """Handle ``lc`` until ``states`` holds one of the run's own session (the
    controller probes the plant with a link of its own first): its commands are
    answered (command_seq above HELLO, OPEN, CLOSE). Returns the newest state."""
    deadline = time.monotonic() + 60
    while not any(s.session != 0 and s.command_seq > 10 and not s.watchdog_tripped
                  for s in states):
        assert time.monotonic() < deadline and run.poll() is None, run.communicate()
        lc.handle_timeout(50)
    return states[-1]


@pytest.mark.slow
def test_a_realtime_run_counts_foreign_traffic_by_cause_and_warns(tmp_path, scenarios):
    """A real-time run under a neighbour's commands (another session) and forged
    states: it completes; metrics.csv's refused counts are what was sent; the
    plant's own count cross-checks the commands; the run ends with a warning."""
    import csv
    import os
    import sys
    import threading

    url, prefix = private_lcm_url(), private_prefix()
    plant = subprocess.Popen([str(plant_binary()), "--lcm-url", url, "--prefix", prefix,
                              "--scenario", str(scenarios / "single.toml"),
                              "--steps-per-interval", "128", "--mode", "realtime", "--rate", "20"],
                             stderr=subprocess.DEVNULL)
    out = tmp_path / "rt"
    run = subprocess.Popen(
        [sys.executable, "-m", "ftc.controller", "--attach", "--method", "closed", "--lcm-url",
         url, "--prefix", prefix, "--intervals", "1", "--steps-per-interval", "128", "--out",
         str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO / "python"), "OMP_NUM_THREADS": "1"})
    lc = lcm.LCM(url)
    states: list = []
    lc.subscribe(prefix + "STATE", lambda _c, d: states.append(plant_state_t.decode(d)))
    sent = {"bad decode": 0, "stale": 0, "seq jump": 0, "other session": 0, "commands": 0}
    try:
        session = _run_session_state(lc, states, run).session
        for k in range(5):
            cmd = valve_command_t()
            cmd.session, cmd.seq = session ^ 1, time.time_ns() // 1000
            cmd.num_valves, cmd.valve = 6, [1] * 6
            lc.publish(prefix + "COMMAND", cmd.encode())
            sent["commands"] += 1
            lc.publish(prefix + "STATE", _state(session, 2**62))
            sent["seq jump"] += 1
            lc.publish(prefix + "STATE", _state(session, 1))
            sent["stale"] += 1
            lc.publish(prefix + "STATE", _state(session ^ 1, 10**9))
            sent["other session"] += 1
            lc.publish(prefix + "STATE", b"\x01" * 50)
            sent["bad decode"] += 1
            time.sleep(0.2)
        stdout, stderr = run.communicate(timeout=120)
    finally:
        run.kill()
        plant.kill()
        plant.wait()
    assert run.returncode == 0, stderr
    with open(out / "metrics.csv") as f:
        (row,) = list(csv.DictReader(f))
    for cause in ("bad decode", "stale", "seq jump", "other session"):
        assert int(row["refused_" + cause.replace(" ", "_")]) == sent[cause], (
            cause, {k: v for k, v in row.items() if "refused" in k or "foreign" in k}, stderr)
    assert int(row["plant_other_session"]) == sent["commands"]  # the plant's own count
    assert row["foreign_commands"] == "0"
    warning = [line for line in stderr.splitlines() if "warning: foreign traffic" in line]
    assert len(warning) == 1 and "the plant refused 5 commands of other sessions" in warning[0]


# ---------------------------------------------------------------------------
# Authentication: a process without the key changes nothing
# ---------------------------------------------------------------------------

def test_python_signing_matches_rfc_4231_and_refuses_tamper_replay_and_stale(tmp_path):
    import hashlib
    import hmac

    from ftc.plant.signing import Auth, load_key

    # RFC 4231 test case 2 through the MAC the bus uses (hmac + sha256)
    assert hmac.new(b"Jefe", b"what do ya want for nothing?", hashlib.sha256).hexdigest() == \
        "5bdcc146bf60754e6a042426089575c75a003f089d2739839dec58b964ec3843"
    key, now = bytes(range(32)), 1_760_000_000_000_000

    def receiver_since(start: int = 0) -> Auth:  # a receiver that started at `start`
        return Auth(key, not_before_us=start)

    sender, receiver = Auth(key), receiver_since()
    msg = sender.sign("X_COMMAND", b"payload", now)
    assert receiver.verify("X_COMMAND", msg, now) == (b"payload", "")
    assert receiver.verify("X_COMMAND", msg, now) == (None, "replay")
    for i in range(len(msg)):
        bad = bytearray(msg)
        bad[i] ^= 1
        assert receiver_since().verify("X_COMMAND", bytes(bad), now)[1] == "bad signature"
    assert receiver_since().verify("X_CONTROL", msg, now)[1] == "bad signature"
    assert receiver_since().verify("X_COMMAND", b"payload", now)[1] == "bad signature"
    late = sender.sign("X_COMMAND", b"payload", now)
    assert receiver_since().verify("X_COMMAND", late, now + 31_000_000)[1] == "old timestamp"
    # signed before the receiver started (a restarted one): a replay, though never
    # seen; signed after: taken. By default a receiver starts with its process.
    before = sender.sign("X_COMMAND", b"payload", now + 1_000)
    after = sender.sign("X_COMMAND", b"payload", now + 3_000)
    assert receiver_since(now + 2_000).verify("X_COMMAND", before, now + 4_000) == (None, "replay")
    assert receiver_since(now + 2_000).verify("X_COMMAND", after, now + 4_000)[1] == ""
    assert Auth(key).verify("X_COMMAND", after, now + 4_000) == (None, "replay")
    assert Auth(key).verify("X_COMMAND", Auth(key).sign("X_COMMAND", b"p"))[1] == ""
    path = tmp_path / "key"
    path.write_text(key.hex())
    path.chmod(0o640)
    with pytest.raises(ValueError, match="readable or writable by others"):
        load_key(path)
    path.chmod(0o600)
    assert load_key(path) == key


def _signed_run(scenarios, attack: bool) -> tuple[list, dict]:
    """30 lockstep steps on a plant with a per-run key; with ``attack``, a
    process without the key that knows the session and the next seq sends
    commands, START, RESET, SHUTDOWN, CLOSE, forged states, tampered and
    replayed copies of the controller's own signed commands."""
    sent = {"unsigned": 0, "tampered": 0, "replayed": 0, "forged states": 0}
    with launch(scenarios / "single.toml", 3, extra_args=["--steps-per-interval", "40"],
                sign=True) as plant:
        assert "FTC_BUS_KEY" not in " ".join(plant.process.args)  # not on the command line
        lc = lcm.LCM(plant.url)
        captured: list[bytes] = []
        lc.subscribe(plant.prefix + "COMMAND", lambda _c, d: captured.append(d))
        obs = [plant.reset()]
        rng = np.random.default_rng(0)
        for t in range(30):
            if attack and t % 10 == 5:
                # the controller's last commands, as the bus delivered them to this
                # process: on a loaded machine the loopback's delivery can lag the
                # lockstep (once none of 5 had arrived when a bare drain ran)
                deadline = time.monotonic() + 10
                while len(captured) < t and time.monotonic() < deadline:
                    lc.handle_timeout(50)
                while lc.handle_timeout(0) > 0:
                    pass
                assert len(captured) >= 3, f"{len(captured)} of the controller's commands heard"
                cmd = valve_command_t()
                cmd.session, cmd.seq = plant.session, plant._seq + 1  # exactly the next one
                cmd.num_valves, cmd.valve = 6, [1, 1, 1, 0, 0, 0]
                lc.publish(plant.prefix + "COMMAND", cmd.encode())
                sent["unsigned"] += 1
                for command in (plant_control_t.START, plant_control_t.RESET,
                                plant_control_t.SHUTDOWN, plant_control_t.CLOSE):
                    msg = plant_control_t()
                    msg.session, msg.seq, msg.command = plant.session, plant._seq + 1, command
                    lc.publish(plant.prefix + "CONTROL", msg.encode())
                    sent["unsigned"] += 1
                for old in captured[-3:]:  # the controller's own, signed: replayed
                    lc.publish(plant.prefix + "COMMAND", old)
                    sent["replayed"] += 1
                tampered = bytearray(captured[-1])
                tampered[-30] ^= 1  # a valve
                lc.publish(plant.prefix + "COMMAND", bytes(tampered))
                sent["tampered"] += 1
                lc.publish(plant.prefix + "STATE", _state(plant.session, plant.last_state.seq + 1))
                sent["forged states"] += 1
            obs.append(plant.step(rng.integers(0, 2, 6)))
        plant.hello()
        counts = {"plant bad signature": int(plant.last_state.bad_signature),
                  "plant replayed": int(plant.last_state.replayed),
                  "link bad signature": plant.refused["bad signature"]}
        assert plant.process.poll() is None
    return obs, {**sent, **counts}


def test_with_a_key_a_process_without_it_changes_nothing(scenarios):
    undisturbed, quiet = _signed_run(scenarios, False)
    disturbed, counts = _signed_run(scenarios, True)
    assert quiet["plant bad signature"] == quiet["plant replayed"] == 0
    for a, b in zip(undisturbed, disturbed, strict=True):  # lockstep: identical
        assert np.array_equal(a.true_level, b.true_level) and a.step == b.step
        assert np.array_equal(a.valves, b.valves)
    # the refused counts equal what was sent
    assert counts["plant bad signature"] == counts["unsigned"] + counts["tampered"] == 3 * 6
    assert counts["plant replayed"] == counts["replayed"] == 3 * 3
    assert counts["link bad signature"] == counts["forged states"] == 3


def test_with_a_key_the_policy_node_flies_only_signed_states_and_pushes(tmp_path, scenarios):
    import sys

    from ftc.plant.signing import new_key

    url, prefix = private_lcm_url(), private_prefix()
    key_file = tmp_path / "bus.key"
    key_file.write_text(new_key().hex())
    key_file.chmod(0o600)
    weights = tmp_path / "p.txt"
    pw.write_weights(weights, [6, 6], np.zeros(42, np.float32), version=1)
    plant = subprocess.Popen([str(plant_binary()), "--scenario", str(scenarios / "single.toml"),
                              "--mode", "realtime", "--rate", "50", "--lcm-url", url,
                              "--prefix", prefix, "--key-file", str(key_file)],
                             stderr=subprocess.DEVNULL)
    node = subprocess.Popen([str(policy_node_binary()), "--policy", str(weights), "--lcm-url",
                             url, "--prefix", prefix, "--steps", "150", "--key-file",
                             str(key_file)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    lc = lcm.LCM(url)
    commands: list = []
    lc.subscribe(prefix + "COMMAND", lambda _c, d: commands.append(d))
    try:
        deadline = time.monotonic() + 20
        while len(commands) < 20:
            assert time.monotonic() < deadline and node.poll() is None, "the node does not fly"
            lc.handle_timeout(50)
        # a neighbour without the key: a well-formed push with a correct checksum
        # and version 2**62 (it was flown, then blocked every later push), forged
        # states, and the node's own signed commands replayed to the plant
        forged = pw.policy_message([6, 6], np.ones(42, np.float32), version=2**62)
        refused = pw.push(url, prefix, forged, timeout=1.0)
        for seq in (2**62, 10**6):
            lc.publish(prefix + "STATE", _state(0, seq))
        for data in commands[:5]:
            lc.publish(prefix + "COMMAND", data)
        signed = subprocess.run(
            [sys.executable, "-m", "ftc.tools.policy_weights", "push", str(weights), "--version",
             "2", "--lcm-url", url, "--prefix", prefix, "--key-file", str(key_file)],
            cwd=REPO, capture_output=True, text=True, timeout=60)
        out, err = node.communicate(timeout=30)
    finally:
        node.kill()
        plant.kill()
        plant.wait()
    # refused unread: its signed answer names no version (the neighbour cannot
    # even tell); the node kept flying version 1, then took the signed push
    assert refused.accepted is None
    assert signed.returncode == 0, signed.stderr
    assert node.returncode == 0 and re.match(r"^steps 150 ", out.strip()), err
    assert float(re.search(r"auth_us_per_step ([\d.]+)", out).group(1)) > 0  # it signed
    assert "policy version 2 in use" in err and f"version {2**62}" not in err
    counts = re.search(r"bad signature (\d+), replay (\d+)", err)
    assert counts and int(counts.group(1)) == 3, err  # the push and the two states


def test_replay_reads_a_keyed_plants_signed_states(tmp_path):
    from ftc.plant.log import read_log
    from ftc.plant.signing import Auth

    auth, path = Auth(bytes(32)), tmp_path / "signed.lcmlog"
    log = lcm.EventLog(str(path), "w", overwrite=True)
    for k in range(11):
        log.write_event(1000 * k, "RUN_STATE", auth.sign("RUN_STATE", _logged_state(k).encode()))
    log.write_event(20_000, "RUN_STATE", b"\x05" * 300)  # a neighbour's garbage
    log.close()
    traj = read_log(path)
    assert len(traj) == 10 and traj.missing == 0 and traj.undecodable == 1


@pytest.mark.slow
def test_with_a_key_a_realtime_run_refuses_everything_a_neighbour_sends(tmp_path, scenarios):
    """ftc.controller --attach --key-file on a real-time plant with the same key
    (docs/deploy.md's setup): a neighbour without the key that reads the session
    off the bus sends commands, START, SHUTDOWN and forged states in it; the
    run completes, takes no step on a command it did not send, and the refused
    counts (the plant's and the link's) equal what was sent."""
    import csv
    import os
    import sys

    from ftc.plant.signing import TRAILER_BYTES, new_key
    from ftc.plant.wire import decode_state

    url, prefix = private_lcm_url(), private_prefix()
    key_file = tmp_path / "bus.key"
    key_file.write_text(new_key().hex())
    key_file.chmod(0o600)
    plant = subprocess.Popen([str(plant_binary()), "--lcm-url", url, "--prefix", prefix,
                              "--scenario", str(scenarios / "single.toml"), "--key-file",
                              str(key_file), "--steps-per-interval", "128", "--mode", "realtime",
                              "--rate", "20"], stderr=subprocess.DEVNULL)
    out = tmp_path / "rt"
    run = subprocess.Popen(
        [sys.executable, "-m", "ftc.controller", "--attach", "--key-file", str(key_file),
         "--method", "closed", "--lcm-url", url, "--prefix", prefix, "--intervals", "1",
         "--steps-per-interval", "128", "--out", str(out)], stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO / "python"), "OMP_NUM_THREADS": "1"})
    lc = lcm.LCM(url)
    states: list = []
    def on_state(_c, data):  # the plant's, signed (the neighbour's own forgeries are not)
        msg, _ = decode_state(data[:-TRAILER_BYTES])
        if msg is not None:
            states.append(msg)

    lc.subscribe(prefix + "STATE", on_state)
    commands = 0
    try:
        last = _run_session_state(lc, states, run)
        session, seq = last.session, last.command_seq
        for k in range(5):
            cmd = valve_command_t()
            cmd.session, cmd.seq, cmd.num_valves, cmd.valve = session, seq + 2 + k, 6, [1] * 6
            lc.publish(prefix + "COMMAND", cmd.encode())
            for command in (plant_control_t.START, plant_control_t.SHUTDOWN):
                msg = plant_control_t()
                msg.session, msg.seq, msg.command = session, seq + 100 + k, command
                lc.publish(prefix + "CONTROL", msg.encode())
            commands += 3
            lc.publish(prefix + "STATE", _state(session, states[-1].seq + 1))
            time.sleep(0.2)
        stdout, stderr = run.communicate(timeout=120)
        while lc.handle_timeout(0) > 0:  # the queue (LCM keeps 30) holds old states
            pass
        end = time.monotonic() + 0.5
        while time.monotonic() < end:
            lc.handle_timeout(50)
        last = states[-1]
    finally:
        run.kill()
        plant.kill()
        plant.wait()
    assert run.returncode == 0, stderr
    with open(out / "metrics.csv") as f:
        (row,) = list(csv.DictReader(f))
    assert row["foreign_commands"] == "0"
    assert int(row["refused_bad_signature"]) == 5  # the forged states
    assert int(last.bad_signature) == commands  # the plant's own count
    assert "the link refused states (5 bad signature)" in stderr


def _control(session: int, seq: int, command: int) -> bytes:
    msg = plant_control_t()
    msg.utime, msg.session, msg.seq, msg.command = time.time_ns() // 1000, session, seq, command
    return msg.encode()


def test_with_a_key_a_restarted_plant_refuses_what_was_signed_before_it_started(tmp_path,
                                                                                 scenarios):
    """A neighbour without the key records a controller's signed OPEN and command
    off the bus, and replays them to a plant restarted with the same key file
    (well within the 30 s window): the new plant has seen no timestamp of that
    link yet, so only its own start time can tell them replays. They are
    refused and counted as replays; the plant neither follows that session nor
    steps."""
    from ftc.plant.signing import TRAILER_BYTES, Auth, new_key

    url, prefix = private_lcm_url(), private_prefix()
    key = new_key()
    key_file = tmp_path / "bus.key"
    key_file.write_text(key.hex())
    key_file.chmod(0o600)
    lc = lcm.LCM(url)
    states: list = []
    lc.subscribe(prefix + "STATE",
                 lambda _c, d: states.append(plant_state_t.decode(d[:-TRAILER_BYTES])))

    def start() -> subprocess.Popen:
        return subprocess.Popen([str(plant_binary()), "--scenario", str(scenarios / "single.toml"),
                                 "--lcm-url", url, "--prefix", prefix, "--key-file",
                                 str(key_file)], stderr=subprocess.PIPE, text=True)

    def ask(auth, channel: str, make, seq: int):
        """Sends a freshly signed make() until the plant answers seq."""
        deadline = time.monotonic() + 20
        while True:
            assert time.monotonic() < deadline, "the plant does not answer"
            lc.publish(prefix + channel, auth.sign(prefix + channel, make()))
            lc.handle_timeout(100)
            answers = [s for s in states if s.command_seq == seq]
            if answers:
                return answers[-1]

    session = 0x5EED
    controller = Auth(key)
    plant = start()
    try:
        ask(controller, "CONTROL", lambda: _control(session, 1, plant_control_t.OPEN), 1)
        cmd = valve_command_t()
        cmd.session, cmd.seq, cmd.num_valves, cmd.valve = session, 2, 6, [1] * 6
        recorded = [controller.sign(prefix + "CONTROL", _control(session, 1, plant_control_t.OPEN)),
                    controller.sign(prefix + "COMMAND", cmd.encode())]
        lc.publish(prefix + "COMMAND", recorded[1])
        stepped = ask(controller, "CONTROL", lambda: _control(session, 3, plant_control_t.HELLO), 3)
        assert stepped.step == 1 and stepped.session == session  # the command was applied
        plant.kill()
        plant.wait()
        states.clear()
        plant = start()
        other = Auth(key)  # another keyed party: sees the new plant up
        ask(other, "CONTROL", lambda: _control(0, 1, plant_control_t.HELLO), 1)
        for data, channel in zip(recorded, ("CONTROL", "COMMAND")):
            lc.publish(prefix + channel, data)  # the neighbour's replay, byte for byte
        time.sleep(0.3)
        after = ask(other, "CONTROL", lambda: _control(0, 2, plant_control_t.HELLO), 2)
    finally:
        plant.kill()
        plant.wait()
    assert after.session != session and after.step == 0, "the replayed session was followed"
    assert after.replayed == 2 and after.bad_signature == 0


def test_a_key_file_is_a_small_regular_file_everywhere(tmp_path, scenarios):
    """A directory, a FIFO, an empty or oversized file as --key-file: one line
    naming the file and exit 2 in every process (a directory threw out of the
    policy node's and lcm_echo's main, exit 134; a FIFO blocked every process
    for good). A symbolic link is followed: its target counts."""
    import os

    from ftc.common.build_info import echo_binary
    from ftc.plant.signing import load_key, new_key

    key = new_key()
    cases = {"dir": tmp_path / "dir", "fifo": tmp_path / "fifo", "empty": tmp_path / "empty",
             "big": tmp_path / "big"}
    cases["dir"].mkdir(mode=0o700)
    os.mkfifo(cases["fifo"], 0o600)
    cases["empty"].write_text("")
    cases["big"].write_text(key.hex() * 100)
    good, link = tmp_path / "good", tmp_path / "link"
    good.write_text(key.hex() + "\n")
    for p in (cases["empty"], cases["big"], good):
        p.chmod(0o600)
    link.symlink_to(good)
    assert load_key(link) == key
    expected = {"dir": "not a regular file", "fifo": "not a regular file",
                "empty": "at least 32 hex digits", "big": "6400 bytes"}
    url = private_lcm_url()
    for name, path in cases.items():
        with pytest.raises(ValueError, match=f"{path}: .*{expected[name]}"):
            load_key(path)
        for cmd in ([str(policy_node_binary()), "--policy", str(tmp_path / "p.txt")],
                    [str(echo_binary())],
                    [str(plant_binary()), "--scenario", str(scenarios / "single.toml")]):
            run = subprocess.run(cmd + ["--lcm-url", url, "--key-file", str(path)],
                                 capture_output=True, text=True, timeout=10)
            lines = run.stderr.strip().splitlines()
            assert run.returncode == 2 and len(lines) == 1, (cmd[0], name, run.stderr)
            assert str(path) in lines[0] and expected[name] in lines[0], lines


def test_a_forged_ack_is_seen_as_conflicting_answers_not_taken(tmp_path):
    """Without a key a neighbour answers every push 'accepted' before the node:
    a push of NaN weights with a correct checksum (which the node rejects) was
    reported accepted. The node's own answer contradicts the forger's: the push
    reports the conflict (no verdict), and the push tool exits 1."""
    import sys
    import threading

    from ftc.policy_ack_t import policy_ack_t

    url, prefix = private_lcm_url(), private_prefix()
    path = tmp_path / "p.txt"
    pw.write_weights(path, [6, 6], np.zeros(42, np.float32), version=1)
    params = np.zeros(42, np.float32)
    params[7] = np.nan
    bad = tmp_path / "nan.txt"
    pw.write_weights(bad, [6, 6], params, version=9)
    node = subprocess.Popen([str(policy_node_binary()), "--policy", str(path), "--lcm-url", url,
                             "--prefix", prefix], stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    stop = threading.Event()

    def forger():
        lc = lcm.LCM(url)

        def answer(_c, data):
            m = policy_t.decode(data)
            ack = policy_ack_t()
            ack.version, ack.push_utime, ack.accepted, ack.reason = m.version, m.utime, True, ""
            lc.publish(prefix + "POLICY_ACK", ack.encode())

        lc.subscribe(prefix + "POLICY", answer)
        while not stop.is_set():
            lc.handle_timeout(20)

    thread = threading.Thread(target=forger)
    thread.start()
    try:
        time.sleep(0.5)  # both subscribed
        outcome = pw.push(url, prefix, pw.policy_message([6, 6], params, version=9), timeout=2)
        tool = subprocess.run([sys.executable, "-m", "ftc.tools.policy_weights", "push", str(bad),
                               "--lcm-url", url, "--prefix", prefix], cwd=REPO,
                              capture_output=True, text=True, timeout=60)
    finally:
        stop.set()
        thread.join()
        node.send_signal(2)
        _, err = node.communicate(timeout=10)
    assert "rejected policy version 9: parameter 7 is not finite" in err
    assert outcome.accepted is None and outcome.conflict, outcome
    assert "conflicting answers" in outcome.describe() and "not finite" in outcome.describe()
    assert tool.returncode == 1 and "conflicting answers" in tool.stderr, tool.stderr


# liblcm reassembles a fragmented message in a buffer of the size its first
# fragment declares (at most LCM_MAX_MESSAGE_SIZE, 256 MB) and keeps up to
# 16 MB of other partial messages: what a receiver can be made to hold before
# any code of ours sees a byte (docs/deploy.md, "Memory").
LIBLCM_REASSEMBLY_MB = 256 + 16


@pytest.mark.slow
def test_an_oversize_fragmented_message_never_completed_is_liblcms_memory_not_more(tmp_path):
    """A neighbour sends raw LCM fragments of a 200 MB policy_t on the node's
    POLICY channel, all but the last, paced so that the kernel drops few: the
    node keeps running, and its peak RSS stays under its own bound plus what
    liblcm's reassembly may hold (measured 114 MB)."""
    import socket

    url, prefix = private_lcm_url(), private_prefix()
    group, port = re.match(r"udpm://([\d.]+):(\d+)", url).groups()
    path = tmp_path / "p.txt"
    pw.write_weights(path, [6, 6], np.zeros(42, np.float32), version=1)
    node = subprocess.Popen([str(policy_node_binary()), "--policy", str(path), "--lcm-url", url,
                             "--prefix", prefix], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)  # this host only
    try:
        time.sleep(1.0)  # subscribed
        total, size = 200 << 20, 60_000
        count = (total + size - 1) // size
        channel = (prefix + "POLICY").encode() + b"\0"
        for i in range(count - 1):  # LCM's long header: magic "LC03", seqno, size, offset, no, of
            header = struct.pack(">IIIIHH", 0x4C433033, 7, total, i * size, i, count)
            sock.sendto(header + (channel if i == 0 else b"") + b"\x11" * size,
                        (group, int(port)))
            if i % 4 == 0:
                time.sleep(0.002)
        time.sleep(0.5)
        assert node.poll() is None
        peak = _peak_rss_mb(node.pid)
        # and it still takes (and answers) a push
        answer = pw.push(url, prefix, pw.policy_message([6, 6], np.zeros(42, np.float32), 2))
    finally:
        sock.close()
        node.send_signal(2)
        node.communicate(timeout=10)
    assert answer.accepted, answer
    assert peak < NODE_RSS_BOUND_MB + LIBLCM_REASSEMBLY_MB, f"peak RSS {peak:.0f} MB"
