"""build/policy_node, the embedded controller: the weights file's arithmetic
is the policy's deterministic action; the node flies it on the real plant in
real-time mode over LCM, acting on every state with the policy it holds; a
pushed policy takes over at a step boundary; a corrupted or stale push is
rejected with a logged reason and the old policy kept; a bad weights file is
refused with one line."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import lcm
import numpy as np
import pytest
import torch
from bus_tap import BusTap

from ftc.common.build_info import plant_binary, policy_node_binary
from ftc.common.errors import UsageError
from ftc.learning.ppo import ActorCritic
from ftc.plant import private_lcm_url, private_prefix
from ftc.tools import policy_weights as pw

REPO = Path(__file__).resolve().parents[2]
SUMMARY = re.compile(r"^steps (\d+) deadline_misses (\d+) latency_p50_us (\d+) "
                     r"latency_p99_us (\d+) latency_max_us (\d+) auth_us_per_step ([\d.]+)$")


def _policy(seed: int) -> tuple[list[int], np.ndarray]:
    torch.manual_seed(seed)
    policy = ActorCritic()
    with torch.no_grad():  # logits of a useful size (a fresh head's are ~0.01)
        head = [m for m in policy.policy_head.modules() if isinstance(m, torch.nn.Linear)][-1]
        head.weight.mul_(300.0)
    return pw.actor_layers(policy)


def test_the_formats_arithmetic_is_the_policys_deterministic_action():
    torch.manual_seed(0)
    policy = ActorCritic()
    with torch.no_grad():
        head = [m for m in policy.policy_head.modules() if isinstance(m, torch.nn.Linear)][-1]
        head.weight.mul_(300.0)
    widths, params = pw.actor_layers(policy)
    assert widths == [6, 64, 64, 16, 16, 6]
    levels = np.random.default_rng(0).uniform(0, 1, (2000, 6))
    with torch.no_grad():
        logits, _ = policy(torch.as_tensor(levels, dtype=torch.float32))
    expected = (logits > 0).numpy().astype(np.int8)
    # float32 in both; rows whose logit is within rounding of 0 may differ
    close = (np.abs(logits.numpy()) < 1e-4).any(axis=1)
    assert np.array_equal(pw.actions(widths, params, levels)[~close], expected[~close])
    assert 0.1 < expected.mean() < 0.9  # both valve states occur: the check means something


def test_a_weights_file_round_trips_and_damage_is_named(tmp_path):
    widths, params = _policy(1)
    path = tmp_path / "p.txt"
    pw.write_weights(path, widths, params, version=3)
    w, p, v = pw.read_weights(path)
    assert (w, v) == (widths, 3) and np.array_equal(p, params)  # 9 digits: float32 exactly
    text = path.read_text().splitlines()
    text[5] = text[5].replace(text[5].split()[0], "0.5", 1)  # one weight changed
    path.write_text("\n".join(text) + "\n")
    with pytest.raises(UsageError, match="checksum mismatch"):
        pw.read_weights(path)
    lines = pw.format_weights(widths, params).splitlines()
    path.write_text("\n".join(lines[:7] + lines[-1:]) + "\n")  # params cut, checksum kept
    with pytest.raises(UsageError, match="truncated"):
        pw.read_weights(path)
    path.write_text("\n".join(lines[:7]) + "\n")  # cut before the checksum line
    with pytest.raises(UsageError, match="missing or malformed"):
        pw.read_weights(path)


def test_the_node_refuses_a_bad_weights_file_with_one_line(tmp_path):
    widths, params = _policy(1)
    path = tmp_path / "p.txt"
    path.write_text(pw.format_weights(widths, params).replace("checksum ", "checksum 1"))
    out = subprocess.run([str(policy_node_binary()), "--policy", str(path), "--lcm-url", private_lcm_url()],
                         capture_output=True, text=True, timeout=30)
    assert out.returncode == 2
    assert out.stderr.count("\n") == 1 and "checksum mismatch" in out.stderr


@pytest.mark.parametrize("value", ["-1", "1001", "soon"])
def test_the_node_refuses_a_bad_warm_up_lead(tmp_path, value):
    widths, params = _policy(1)
    path = tmp_path / "p.txt"
    path.write_text(pw.format_weights(widths, params))
    out = subprocess.run([str(policy_node_binary()), "--policy", str(path), "--lcm-url",
                          private_lcm_url(), "--warm-ms", value],
                         capture_output=True, text=True, timeout=30)
    assert out.returncode == 2 and "--warm-ms" in out.stderr, out.stderr


@pytest.mark.subprocess
def test_the_node_flies_the_policy_and_takes_a_push_at_a_step_boundary(tmp_path, scenarios):
    url, prefix = private_lcm_url(), private_prefix()
    first, second = _policy(1), _policy(2)
    path = tmp_path / "p.txt"
    pw.write_weights(path, *first, version=1)
    bus = BusTap(url, prefix)
    plant = subprocess.Popen([str(plant_binary()), "--scenario", str(scenarios / "single.toml"),
                              "--mode", "realtime", "--rate", "50", "--watchdog", "1",
                              "--lcm-url", url, "--prefix", prefix], stderr=subprocess.PIPE)
    node = subprocess.Popen([str(policy_node_binary()), "--policy", str(path), "--lcm-url", url, "--prefix",
                             prefix, "--steps", "150"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 20
        while len(bus.commands) < 50:
            assert time.monotonic() < deadline, "no commands from the node on the bus"
            time.sleep(0.02)
        pushed_at = max(bus.states)
        outcomes = [pw.push(url, prefix, pw.policy_message(*second, version=2))]
        time.sleep(0.3)
        outcomes.append(pw.push(url, prefix, pw.policy_message(*first, version=3,
                                                               checksum_value=12345)))
        # not above the running 2
        outcomes.append(pw.push(url, prefix, pw.policy_message(*first, version=1)))
        out, err = node.communicate(timeout=30)
    finally:
        node.kill()
        plant.kill()
        plant.wait()
        bus.stop = True
    summary = SUMMARY.match(out.strip())
    assert summary and int(summary.group(1)) == 150, out
    assert float(summary.group(6)) == 0.0  # no key: no time in HMAC
    assert "policy version 2 in use" in err
    assert "rejected policy version 3: checksum mismatch" in err
    assert "rejected policy version 1: version 1 is not above the running 2" in err
    # each push was answered on the ack channel with what the node did
    assert [(o.version, o.accepted) for o in outcomes] == [(2, True), (3, False), (1, False)]
    assert outcomes[1].reason.startswith("checksum mismatch")
    assert outcomes[2].reason == "version 1 is not above the running 2"
    # every command is the action of the policy in use for the state it answers:
    # the first up to the push, the second after it, never a mixture within a step
    switched = None
    for state_seq, valves in bus.commands:
        level = bus.states[state_seq][0][None]
        old = pw.actions(*first, level)[0]
        new = pw.actions(*second, level)[0]
        if np.array_equal(old, new):
            continue  # both policies agree here: says nothing about which acted
        assert np.array_equal(valves, old) or np.array_equal(valves, new)
        if np.array_equal(valves, new):
            switched = state_seq if switched is None else switched
        else:
            assert switched is None, "the old policy acted after the new one had"
            assert state_seq <= pushed_at + 20
    assert switched is not None and switched > pushed_at - 1


@pytest.mark.subprocess
def test_a_learning_run_pushes_its_policy_to_a_running_node_after_every_interval(
        tmp_path, scenarios):
    # with a bus key (plant, node and the learner's pushes: --push-key-file), as
    # docs/deploy.md sets it up; pw.push's unsigned path is tested above
    from ftc.plant.signing import TRAILER_BYTES, new_key

    url, prefix = private_lcm_url(), private_prefix()
    key_file = tmp_path / "bus.key"
    key_file.write_text(new_key().hex())
    key_file.chmod(0o600)
    path = tmp_path / "p.txt"
    pw.write_weights(path, *_policy(1), version=1)
    plant = subprocess.Popen([str(plant_binary()), "--scenario", str(scenarios / "single.toml"),
                              "--mode", "realtime", "--rate", "50", "--watchdog", "1",
                              "--lcm-url", url, "--prefix", prefix, "--key-file", str(key_file)],
                             stderr=subprocess.DEVNULL)
    node = subprocess.Popen([str(policy_node_binary()), "--policy", str(path), "--lcm-url", url,
                             "--prefix", prefix, "--key-file", str(key_file)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    from ftc.policy_t import policy_t
    pushed = []
    lc = lcm.LCM(url)
    lc.subscribe(prefix + "POLICY",
                 lambda _c, data: pushed.append(policy_t.decode(data[:-TRAILER_BYTES])))
    try:
        time.sleep(0.5)  # the node subscribed
        # the learner runs elsewhere (here in process, lockstep) and flies nothing itself
        run = subprocess.run(
            [sys.executable, "-m", "ftc.controller", "--link", "core", "--intervals", "2",
             "--steps-per-interval", "64", "--update-every", "32", "--no-offline", "--quiet",
             "--push-policy", prefix, "--push-url", url, "--push-key-file", str(key_file),
             "--out", str(tmp_path / "run")],
            cwd=REPO, capture_output=True, text=True, timeout=300)
        time.sleep(0.3)  # the last push reaches the node between two of its steps
        while lc.handle_timeout(10) > 0:
            pass
        node.send_signal(signal.SIGINT)
        out, err = node.communicate(timeout=30)
    finally:
        node.kill()
        plant.kill()
        plant.wait()
    assert run.returncode == 0, run.stderr[-2000:]
    taken = re.findall(r"policy version (\d+) in use", err)
    assert len(taken) == 2, err  # one push per interval, each newer than the last
    assert "bad signature 0" in err or "refused messages" not in err, err  # all signed
    assert int(taken[0]) < int(taken[1])
    assert "rejected" not in err
    # the last push carries the run's final policy, as ftc.export writes it
    checkpoint = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    policy = ActorCritic()
    policy.load_state_dict(checkpoint["agent"]["ppo"]["policy"])
    widths, params = pw.actor_layers(policy)
    assert [m.version for m in pushed] == [int(v) for v in taken]
    # metrics.csv records each push's outcome, as the node answered it
    import csv
    with open(tmp_path / "run" / "metrics.csv") as f:
        rows = list(csv.DictReader(f))
    assert [(int(r["push_version"]), r["push_accepted"], r["push_reason"]) for r in rows] == \
        [(int(v), "1", "") for v in taken]
    assert list(pushed[-1].widths) == widths
    assert np.array_equal(np.array(pushed[-1].params, np.float32), params)
    assert not np.array_equal(np.array(pushed[0].params, np.float32), params)  # it learned


def test_push_key_file_needs_push_policy_and_a_private_key_file(tmp_path):
    from ftc.control.agents.ppo import ControllerConfig

    key = tmp_path / "bus.key"
    key.write_text("ab" * 32)
    key.chmod(0o600)
    ControllerConfig(push_policy="RT_", push_key_file=str(key)).validate()
    with pytest.raises(ValueError, match="--push-key-file has no effect without --push-policy"):
        ControllerConfig(push_key_file=str(key)).validate()
    key.chmod(0o644)  # (a config's ValueError is the command line's one-line exit 2)
    with pytest.raises(ValueError, match="--push-key-file .*readable or writable by others"):
        ControllerConfig(push_policy="RT_", push_key_file=str(key)).validate()


def test_push_policy_refuses_a_method_without_a_policy(tmp_path):
    run = subprocess.run([sys.executable, "-m", "ftc.controller", "--method", "closed",
                          "--link", "core", "--intervals", "1", "--push-policy", "RT_",
                          "--out", str(tmp_path / "run")], cwd=REPO, capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 2
    assert "--push-policy is not an option of --method closed" in run.stderr
    assert not (tmp_path / "run" / "config.json").exists()


def test_the_push_tool_exits_non_zero_on_a_rejection_or_no_answer(tmp_path):
    url, prefix = private_lcm_url(), private_prefix()
    path = tmp_path / "p.txt"
    pw.write_weights(path, *_policy(1), version=5)
    push = [sys.executable, "-m", "ftc.tools.policy_weights", "push", str(path), "--lcm-url", url,
            "--prefix", prefix, "--timeout", "0.5"]
    nobody = subprocess.run(push, cwd=REPO, capture_output=True, text=True, timeout=60)
    assert nobody.returncode == 1 and "no answer from a policy node" in nobody.stderr
    node = subprocess.Popen([str(policy_node_binary()), "--policy", str(path), "--lcm-url", url,
                             "--prefix", prefix], stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        time.sleep(0.5)  # subscribed
        stale = subprocess.run(push, cwd=REPO, capture_output=True, text=True, timeout=60)
        newer = subprocess.run(push + ["--version", "6"], cwd=REPO, capture_output=True,
                               text=True, timeout=60)
    finally:
        node.send_signal(signal.SIGINT)
        node.wait(timeout=10)
    assert stale.returncode == 1
    assert stale.stderr.strip().endswith("rejected: version 5 is not above the running 5")
    assert newer.returncode == 0 and "accepted" in newer.stdout, newer.stderr
