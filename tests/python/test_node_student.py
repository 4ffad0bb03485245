"""The adaptive student on build/policy_node: exported with its history window
(``ftc-policy 2``), flown on the real plant in real-time mode over LCM with
the actions Python's student takes on the same states, step by step, across
episode starts; pushed as a ``policy_v2_t`` (signed with a bus key too), with
damaged pushes refused by name and policy_t pushes taken as before."""

from __future__ import annotations

import re
import signal
import subprocess
import time
from pathlib import Path

import lcm
import numpy as np
import pytest
import torch
from bus_tap import BusTap

from ftc.common.build_info import BUILD_DIR, plant_binary, policy_node_binary
from ftc.common.errors import UsageError
from ftc.learning.history_policy import HistoryPolicy, HistoryWindow, StudentConfig, ensemble
from ftc.learning.ppo import ActorCritic
from ftc.plant import private_lcm_url, private_prefix
from ftc.tools import policy_weights as pw
from ftc.tools.export import main as export_main

# valve 2 sticks closed and valve 5 open early in the run (operating steps)
STUCK_EVENTS = """
[[event]]
at_step = 10
stuck_valve = 2
state = "closed"

[[event]]
at_step = 30
stuck_valve = 5
state = "open"
"""
SUMMARY = re.compile(r"^steps (\d+) deadline_misses (\d+) ")
# float32 in both, but torch and Eigen sum the 144 products of a unit in other
# orders (and other BLAS kernels per CPU): logits agree to ~1e-6 of their
# terms, so a logit this close to 0 may open the valve on one side only (the
# valves head), or two logits this close may swap places (the joint head)
NEAR_TIE = 1e-4


def _student(seed: int, window: int = 12, head: str = "valves",
             stuck_memory: bool = False) -> HistoryPolicy:
    """An untrained student of the trained one's architecture (window 12,
    128 x 128 tanh), its output layer scaled up so that its logits are far from 0
    and from each other (a fresh layer's are ~0.1) and its valves change with
    the history."""
    torch.manual_seed(seed)
    student = HistoryPolicy(StudentConfig(window=window, hidden=(128, 128), head=head,
                                          stuck_memory=stuck_memory))
    with torch.no_grad():
        student.net[-1].weight.mul_(30.0)
    return student.eval()


def _export(student: HistoryPolicy, tmp_path: Path, name: str) -> Path:
    """The student through ftc.export, as a checkpoint of the train command holds it."""
    checkpoint, weights = tmp_path / f"{name}.pt", tmp_path / f"{name}.txt"
    torch.save({"policy": student.record(), "config": {}}, checkpoint)
    assert export_main([str(checkpoint), "--weights", str(weights)]) == 0
    return weights


def _replay(student: HistoryPolicy, bus: BusTap, reverse: bool = False,
            forget: bool = False):
    """Python's student on the states the node acted on, in order: the window
    started where the real-time loop starts an episode (the first state, a
    state of step 0 or of another episode) and pushed with the command sent on
    the state before otherwise (ftc.control.run.realtime with the adaptive
    agent). Returns its valves per command and whether each is firm (no
    logit within NEAR_TIE of 0, or with the joint head the top two logits
    NEAR_TIE apart or more); ``reverse`` feeds the window oldest first (what a
    node with its order broken would compute). With the stuck memory, a
    state's applied valves enter it when the state answers the command before
    and the watchdog was not holding the valves (the node's rule); ``forget``
    clears it before every step (what a node without it would compute).
    Returns the valves, the firm flags and the stuck memory at the end (or
    None)."""
    window = HistoryWindow(1, student.config.window, student.config.stuck_memory)
    valves, firm, episode, last, last_seq = [], [], None, None, None
    for (state_seq, sent), seq in zip(bus.commands, bus.command_seqs):
        level, step, ep = bus.states[state_seq]
        if last is None or step == 0 or ep != episode:
            window.start(level[None])
        else:
            applied, answers, watchdog = bus.answers[state_seq]
            if answers != last_seq or watchdog:
                applied = last  # a step on an older command or the safe state
            window.push(level[None], last[None], applied=applied[None])
        if forget:
            window.forget()
        x = window.features()
        if reverse:  # the window's steps in the other order (the memory after them as is)
            w = 12 * student.config.window
            steps = x[:, :w].reshape(1, student.config.window, -1)[:, ::-1].reshape(1, -1)
            x = np.concatenate([steps, x[:, w:]], axis=1)
        with torch.no_grad():
            out = student(torch.as_tensor(x)).numpy()[0]
        valves.append(student.act(x)[0])  # Python's rule for its head
        if student.config.head == "joint":
            top2 = np.sort(out)[-2:]
            firm.append(top2[1] - top2[0] >= NEAR_TIE)
        else:
            firm.append(not (np.abs(out) < NEAR_TIE).any())
        # the node's own command goes into the history (the same as Python's on
        # every step asserted below; at a near tie it keeps the two in step)
        episode, last, last_seq = ep, sent, seq
    memory = None if window.stuck is None else window.stuck[0].copy()
    return np.array(valves), np.array(firm), memory


@pytest.mark.quick
@pytest.mark.parametrize("head,members,memory", [("valves", 1, False), ("joint", 1, False),
                                                 ("joint", 3, False), ("joint", 4, True)])
def test_the_node_flies_the_student_with_pythons_actions_on_every_step(tmp_path, scenarios,
                                                                       head, members, memory):
    # several members: a middle layer the node flies as packed blocks (the zeros
    # between them skipped); four with the stuck memory, the default's shape, on a
    # plant whose valves stick early (one open, one closed)
    student = (_student(0, head=head, stuck_memory=memory) if members == 1
               else ensemble([_student(seed, head=head, stuck_memory=memory)
                              for seed in range(members)]).eval())
    weights = _export(student, tmp_path, "student")
    policy = pw.read_policy(weights)
    assert policy.window == 12 and policy.widths[-1] == student.config.outputs
    assert policy.stuck_memory == memory
    scenario = scenarios / "single.toml"
    if memory:
        scenario = tmp_path / "stuck.toml"
        scenario.write_text((scenarios / "single.toml").read_text() + STUCK_EVENTS)
    url, prefix = private_lcm_url(), private_prefix()
    bus = BusTap(url, prefix)
    # short intervals: the run crosses several episode starts (the window refilled)
    plant = subprocess.Popen([str(plant_binary()), "--scenario", str(scenario),
                              "--mode", "realtime", "--rate", "200", "--watchdog", "1",
                              "--steps-per-interval", "48", "--lcm-url", url, "--prefix",
                              prefix], stderr=subprocess.DEVNULL)
    try:
        node = subprocess.run([str(policy_node_binary()), "--policy", str(weights), "--lcm-url",
                               url, "--prefix", prefix, "--steps", "240"], capture_output=True,
                              text=True, timeout=60)
        # the recorder's thread handles what the bus delivered: on a loaded machine it
        # ran 14 commands behind when a fixed 0.1 s wait ended (226 of 240 recorded)
        deadline = time.monotonic() + 10
        while len(bus.commands) < 240 and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        plant.kill()
        plant.wait()
        bus.stop = True
        bus.thread.join(timeout=5)
    summary = SUMMARY.match(node.stdout.strip())
    assert node.returncode == 0 and summary and int(summary.group(1)) == 240, node.stderr
    assert f"diagonal blocks 1 {members} 1)" in node.stderr, node.stderr
    assert len(bus.commands) == 240
    # the node ran the student once before most states came (--warm-ms, default 1 ms
    # ahead of the 5 ms period; a state that comes early on a loaded machine skips
    # one), and the actions below are checked with those warm-ups in the run
    warm = re.search(r"(\d+) warm-ups before states", node.stderr)
    assert warm and 60 <= int(warm.group(1)) <= 240, node.stderr
    missing = [s for s, _ in bus.commands if s not in bus.states]
    assert not missing, f"states the recorder missed: {missing[:5]}"
    sent = np.array([v for _, v in bus.commands])
    expected, firm, seen = _replay(student, bus)
    assert firm.sum() >= 236, f"{240 - firm.sum()} near ties"  # rare: the test stays a test
    wrong = np.flatnonzero((sent != expected).any(axis=1) & firm)
    assert not len(wrong), (f"the node's valves differ from Python's at commands "
                            f"{wrong[:10].tolist()}: node {sent[wrong[0]]}, Python "
                            f"{expected[wrong[0]]}")
    # what makes the check mean something: episodes started within the run, the
    # valves changed within episodes, and the window's order changes the valves
    starts = sum(bus.states[s][1] == 0 for s, _ in bus.commands)
    assert starts >= 3, starts
    assert 0.05 < sent.mean() < 0.95 and (np.diff(sent, axis=0) != 0).any(axis=1).sum() >= 10
    reversed_valves, _, _ = _replay(student, bus, reverse=True)
    assert (reversed_valves != sent).any(axis=1).sum() >= 10
    if memory:  # it saw both valves stuck, and without the memory the valves differ
        assert seen.tolist() == [0, 1, 0, 0, 0, 0] + [0, 0, 0, 0, 1, 0], seen
        forgetting, _, _ = _replay(student, bus, forget=True)
        assert (forgetting != sent).any(axis=1).sum() >= 5


def test_a_windowed_weights_file_round_trips_and_damage_is_named(tmp_path):
    window, widths, params = pw.student_layers(_student(1, window=3))
    assert (window, widths) == (3, [36, 128, 128, 6])
    path = tmp_path / "s.txt"
    pw.write_weights(path, widths, params, version=4, window=window)
    text = path.read_text()
    assert text.startswith("ftc-policy 2\nversion 4\nwindow 3\nwidths 36 128 128 6\n")
    w = pw.read_policy(path)
    assert (w.window, w.widths, w.version) == (3, widths, 4) and np.array_equal(w.params, params)
    with pytest.raises(UsageError, match="a policy with a history window of 3 steps"):
        pw.read_weights(path)  # the levels-only reader does not drop the window silently
    path.write_text(text.replace("window 3", "window 4"))  # the checksum covers the window
    with pytest.raises(UsageError, match="checksum mismatch"):
        pw.read_policy(path)
    path.write_text(text.replace("window 3\n", ""))
    with pytest.raises(UsageError, match="window, widths, params or checksum line is missing"):
        pw.read_policy(path)
    # a policy of the levels stays an ftc-policy 1 file with the checksum it always had
    levels = pw.actor_layers(ActorCritic())
    pw.write_weights(path, *levels)
    assert path.read_text().startswith("ftc-policy 1\nversion 1\nwidths 6 ")
    assert pw.read_policy(path).window == 0 and pw.read_weights(path)[0] == levels[0]
    assert pw.checksum(*levels) != pw.checksum(*levels, 0)


def test_a_weights_file_with_the_stuck_memory_round_trips_and_damage_is_named(tmp_path):
    window, widths, params = pw.student_layers(_student(1, window=2, stuck_memory=True))
    assert (window, widths[0]) == (2, 36)  # 12 per step, then the 12 of the memory
    path = tmp_path / "m.txt"
    pw.write_weights(path, widths, params, version=2, window=window, stuck_memory=True)
    text = path.read_text()
    assert text.startswith("ftc-policy 2\nversion 2\nwindow 2\nstuck_memory 1\nwidths 36 ")
    w = pw.read_policy(path)
    assert w.stuck_memory and w.window == 2 and np.array_equal(w.params, params)
    path.write_text(text.replace("stuck_memory 1\n", ""))  # the checksum covers it
    with pytest.raises(UsageError, match="checksum mismatch"):
        pw.read_policy(path)
    # the window's checksum, the memory's line dropped: its widths are not a window's
    pw.write_weights(path, widths, params, version=2, window=window)
    with pytest.raises(UsageError, match=r"widths must start at 24 \(a window of 2 steps\)"):
        pw.read_policy(path)
    with pytest.raises(ValueError, match="after a history window"):
        pw.format_weights(widths, params, window=0, stuck_memory=True)
    with pytest.raises(ValueError, match="after a history window"):
        pw.policy_message(widths, params, 3, window=0, stuck_memory=True)
    # the file's rule and the student's own input width are one number
    for w, memory in ((1, False), (2, True), (12, True), (50, False)):
        assert pw.window_inputs(w, memory) == StudentConfig(window=w, stuck_memory=memory).inputs
    msg = pw.policy_message(widths, params, 3, window=window, stuck_memory=True)
    assert msg.stuck_memory == 1  # the checksum as int64 on the wire
    assert msg.checksum % 2**64 == pw.checksum(widths, params, 2, True)


def test_export_writes_the_students_weights_only(tmp_path, capsys):
    checkpoint = tmp_path / "student.pt"
    torch.save({"policy": _student(2).record(), "config": {}}, checkpoint)
    assert export_main([str(checkpoint), "--out", str(tmp_path / "s.onnx")]) == 2
    assert "exports as --weights only" in capsys.readouterr().err
    assert not (tmp_path / "s.onnx").exists()
    record = {"policy": _student(2).record(), "config": {}}
    record["policy"]["state"]["net.0.weight"][0, 0] = float("nan")
    torch.save(record, checkpoint)
    assert export_main([str(checkpoint), "--weights", str(tmp_path / "s.txt")]) == 2
    assert "not all finite" in capsys.readouterr().err
    assert not (tmp_path / "s.txt").exists()


def _rmem_max() -> int:
    try:
        return int(Path("/proc/sys/net/core/rmem_max").read_text())
    except (OSError, ValueError):
        return 0


@pytest.mark.skipif(_rmem_max() < 8 << 20, reason=(
    "net.core.rmem_max is below the node's 8 MB receive buffer: a 1.5 MB push can lose "
    "fragments (scripts/setup.sh raises it when run as root)"))
def test_the_default_students_shape_is_pushed_whole(tmp_path):
    # four members with the stuck memory: 375,872 floats (1.5 MB, ~1,100 fragments),
    # within policy_v2_t.MAX_PARAMS
    window, widths, params = pw.student_layers(ensemble(
        [_student(seed, head="joint", stuck_memory=True) for seed in range(4)]))
    assert widths == [156, 512, 512, 64] and len(params) == 375_872
    url, prefix = private_lcm_url(), private_prefix()
    node = subprocess.Popen([str(policy_node_binary()), "--policy",
                             str(_export(_student(3), tmp_path, "first")), "--lcm-url", url,
                             "--prefix", prefix], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    try:
        time.sleep(0.5)  # subscribed
        outcome = pw.push(url, prefix, pw.policy_message(widths, params, 2, window=window,
                                                         stuck_memory=True), timeout=10)
    finally:
        node.send_signal(signal.SIGINT)
        _, err = node.communicate(timeout=10)
    assert outcome.accepted, (outcome.reason, err)
    assert ("policy version 2 in use (widths 156-512-512-64, window 12, stuck memory, "
            "diagonal blocks 1 4 1)") in err, err


def test_the_student_is_pushed_signed_and_bad_pushes_are_refused_by_name(tmp_path, capsys):
    from ftc.plant.signing import new_key

    url, prefix = private_lcm_url(), private_prefix()
    key = new_key()
    key_file = tmp_path / "bus.key"
    key_file.write_text(key.hex())
    key_file.chmod(0o600)
    first = _export(_student(3), tmp_path, "first")
    window, widths, params = pw.student_layers(_student(4))
    joint = pw.student_layers(_student(5, head="joint"))
    second = tmp_path / "second.txt"
    pw.write_weights(second, widths, params, version=2, window=window)
    node = subprocess.Popen([str(policy_node_binary()), "--policy", str(first), "--lcm-url", url,
                             "--prefix", prefix, "--key-file", str(key_file)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(0.5)  # subscribed
        # the tool as the docs run it (an answer comes in milliseconds; the
        # timeout only bounds the wait on a loaded machine)
        push = ["push", str(second), "--lcm-url", url, "--prefix", prefix]
        signed = pw.main([*push, "--key-file", str(key_file), "--timeout", "10"])
        signed_out = capsys.readouterr().out
        unsigned = pw.main([*push, "--version", "3", "--timeout", "0.5"])
        unsigned_err = capsys.readouterr().err
        outcomes = [pw.push(url, prefix, msg, timeout=10, key=key) for msg in (
            pw.policy_message(widths, params, 4, window=window, checksum_value=12345),
            pw.policy_message(widths, params, 5, window=5),  # 144 inputs are not 5 steps
            pw.policy_message(*pw.actor_layers(ActorCritic()), 6),  # policy_t, as before
            pw.policy_message(joint[1], joint[2], 7, window=joint[0]),  # the joint head
            pw.policy_message([144, 65], np.zeros(145 * 65, np.float32), 8, window=12))]
    finally:
        node.send_signal(signal.SIGINT)
        out, err = node.communicate(timeout=10)
    assert signed == 0 and "as version 2 on" in signed_out, err
    assert unsigned == 1 and "no answer" in unsigned_err  # refused, its answer signed
    assert "policy version 2 in use (widths 144-128-128-6, window 12, " in err
    assert [(o.version, o.accepted) for o in outcomes] == [(4, False), (5, False), (6, True),
                                                           (7, True), (8, False)], err
    assert outcomes[0].reason.startswith("checksum mismatch")
    assert outcomes[1].reason == "widths must run from 60 (a window of 5 steps of levels and " \
                                 "valves) to 6 (a logit per valve) or 64 (a logit per " \
                                 "valve setting)"
    assert outcomes[4].reason.endswith("to 6 (a logit per valve) or 64 (a logit per valve "
                                       "setting)")
    assert "bad signature 1" in err


def test_bench_forward_times_an_exported_ensemble_and_refuses_bad_input(tmp_path):
    """build/bench_forward on a two-member student: it finds the members' blocks and
    prints its timings, the node's prepared way among them; --help explains, bad arguments exit 2, a missing file exits 1
    naming it."""
    bench = BUILD_DIR / "bench_forward"
    assert bench.is_file(), f"{bench} missing: scripts/setup.sh builds it"
    weights = _export(ensemble([_student(0, stuck_memory=True), _student(1, stuck_memory=True)]),
                      tmp_path, "pair")
    run = subprocess.run([str(bench), str(weights), "--passes", "10"], capture_output=True,
                         text=True, timeout=60)
    assert run.returncode == 0, run.stderr
    assert "diagonal blocks per layer 1 2 1" in run.stdout, run.stdout
    for way in ("dense", "packed", "prepared"):
        assert re.search(rf"^{way} +cold p50 [\d.]+ us p99 [\d.]+ us", run.stdout, re.M), run.stdout
    assert re.search(r"^prepared / packed: cold p50 [\d.]+", run.stdout, re.M), run.stdout
    shown = subprocess.run([str(bench), "--help"], capture_output=True, text=True, timeout=10)
    assert shown.returncode == 0 and shown.stdout.startswith("usage: bench_forward WEIGHTS")
    for bad in ([], [str(weights), "--passes", "5"], [str(weights), "--pases", "10"]):
        refused = subprocess.run([str(bench), *bad], capture_output=True, text=True, timeout=10)
        assert refused.returncode == 2 and refused.stderr.strip(), (bad, refused)
    missing = subprocess.run([str(bench), str(tmp_path / "none.txt")], capture_output=True,
                             text=True, timeout=10)
    assert missing.returncode == 1 and "none.txt" in missing.stderr, missing.stderr
