"""The real plant process over LCM: :class:`LcmPlant` (lockstep with sequence
checks, retries with back-off, plant-gone detection), :func:`launch` (a private
plant process on a private loopback port and prefix) and :func:`attach`.

A link opens a control session of its own (a random 64-bit id, plant_control_t
OPEN) right after its handshake: the plant then refuses commands of any other
session, and the link ignores (and counts, ``refused``) states of any other
session and buffers that do not decode (:mod:`ftc.plant.wire`)."""

from __future__ import annotations

import os
import random
import secrets
import subprocess
import tempfile
import threading
import time
import warnings
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ftc.common.constants import DEFAULT_LCM_URL, DEFAULT_PREFIX, LCM_MULTICAST_GROUP, NUM_TANKS
from ftc.common.build_info import plant_binary
from ftc.common.lifetime import die_with_parent
from ftc.plant.foreign import ForeignWatch
from ftc.plant.link import (PlantError, PlantGoneError, PlantObservation,
                             valves_array)
from ftc.plant.signing import KEY_VARIABLE, Auth, new_key
from ftc.plant.wire import decode_state


@dataclass(frozen=True)
class LinkConfig:
    """Timing of the lockstep link.

    retry_timeout: seconds to wait for an answer before re-sending the same
        message (the plant re-sends its answer to a repeated seq without stepping)
    give_up_timeout: seconds without any answer after which the plant counts as gone
    startup_timeout: seconds to wait for a newly started plant's first answer
    backoff: factor by which the wait grows after each unanswered re-send of one
        message (1: a fixed retry_timeout; 2: exponential back-off, so a plant that
        is merely slow is not flooded while the give-up time runs out)
    """

    retry_timeout: float = 0.25
    give_up_timeout: float = 5.0
    startup_timeout: float = 10.0
    backoff: float = 1.0


def private_port_range(path: str = "/proc/sys/net/ipv4/ip_local_port_range") -> range:
    """Ports for private LCM URLs: from 20000 up to the kernel's ephemeral range.

    An LCM receive socket shares its port with other LCM sockets (SO_REUSEADDR),
    but not with a socket the kernel gave that port to as an ephemeral one (any
    process's outgoing socket, LCM's own send sockets included): the bind then
    fails ("bind: Address already in use"), which a CI run of the experiments
    hit with ports drawn from 20000-59999 (Linux's ephemeral range is
    32768-60999)."""
    try:
        with open(path) as f:
            low = int(f.read().split()[0])
    except (OSError, ValueError, IndexError):
        low = 32768
    return range(20000, low) if low >= 20000 + 4096 else range(20000, 32768)


def private_lcm_url(port: int | None = None) -> str:
    """A loopback-only multicast URL on a random (or given) port, for one run."""
    port = port if port is not None else random.SystemRandom().choice(private_port_range())
    return f"udpm://{LCM_MULTICAST_GROUP}:{port}?ttl=0"


def private_prefix() -> str:
    """A channel prefix unique to this process and call."""
    return f"FTC{os.getpid()}_{secrets.token_hex(3)}_"


def check_loopback_url(url: str, allow_network: bool = False) -> None:
    """Refuse an LCM URL that may leave this machine unless asked for explicitly."""
    # exactly one ttl option and it is 0: LCM takes the last of repeated options,
    # so "ttl=0&ttl=1" must not pass for loopback
    query = url.partition("?")[2]
    ttls = [opt.partition("=")[2] for opt in query.split("&") if opt.partition("=")[0] == "ttl"]
    loopback = url.startswith("memq://") or (url.startswith("udpm://") and ttls == ["0"])
    if loopback:
        return
    if not allow_network:
        raise ValueError(f"LCM URL '{url}' may leave this machine (udpm needs ttl=0); "
                         "pass allow_network=True / --allow-network to do it on purpose")
    warnings.warn(f"LCM traffic may leave this machine ({url})", stacklevel=2)


def new_session() -> int:
    """A random non-zero session id (int64 on the wire)."""
    while True:
        session = secrets.randbits(64) - (1 << 63)
        if session:
            return session


def exit_message(process, stderr_path: str | None) -> str | None:
    """How a plant process this link started ended (its stderr's tail), or None."""
    if process is None or process.poll() is None:
        return None
    tail = ""
    if stderr_path:
        try:
            with open(stderr_path, errors="replace") as f:
                tail = f.read()[-2000:].strip()
        except OSError:
            pass
    return f"plant process exited with code {process.returncode}" + (f": {tail}" if tail else "")


def foreign_note(refused: dict[str, int], seen, last) -> str:
    """What a link saw besides its plant's answers: ``refused`` counts by
    cause, ``seen`` the newest state of another session, ``last`` the newest
    of its own (whose counters say what the plant refused)."""
    notes = []
    if seen is not None:
        notes.append(f"it saw {refused['other session']} states of another session "
                     f"(newest: session {seen.session}, state {seen.seq}, "
                     f"operating step {seen.operating_steps}): the plant restarted "
                     "or another controller took it over")
    if last is not None and last.other_session:
        notes.append(f"the plant refused {last.other_session} commands of other sessions")
    if refused["bad decode"]:
        notes.append(f"{refused['bad decode']} undecodable messages on its STATE channel")
    return "; ".join(notes)


class LcmPlant:
    """Lockstep link to a plant process over LCM (implements :class:`PlantLink`).

    Every request carries the link's session and a fresh sequence number
    within it (from 1); the plant's answer carries both back. Answers to other
    sequence numbers are ignored; states of other sessions are counted in
    ``refused`` and otherwise ignored. A request not answered within ``retry_timeout`` is re-sent with the
    same seq (the plant answers a repeat without stepping twice); after
    ``give_up_timeout`` without an answer, :class:`PlantGoneError` is raised.

    Once its session is open, it stops (ForeignTrafficError, one line) when the plant
    shows another sender in it (:mod:`ftc.plant.foreign`; a HELLO checks too).
    """

    lockstep_checks = True  # ftc.plant.foreign's checks (a real-time plant ticks alone)

    def __init__(self, lcm_url: str, prefix: str, *, config: LinkConfig = LinkConfig(),
                 process: "subprocess.Popen | None" = None, stderr_path: str | None = None,
                 allow_network: bool = False, key: bytes | None = None) -> None:
        import lcm

        from ftc.plant_control_t import plant_control_t
        from ftc.plant_state_t import plant_state_t
        from ftc.valve_command_t import valve_command_t

        check_loopback_url(lcm_url, allow_network)
        self._types = (plant_state_t, valve_command_t, plant_control_t)
        self.url, self.prefix, self.config = lcm_url, prefix, config
        self._process, self._stderr_path = process, stderr_path
        self._lc = lcm.LCM(lcm_url)
        self._answers: list = []
        self.decode_errors = 0
        self.retries = 0
        self.last_state = None
        self.session = new_session()
        # states refused by cause; `seen` is the newest of another session
        self.refused = {"bad decode": 0, "other session": 0, "stale": 0, "seq jump": 0,
                        "bad signature": 0, "replay": 0, "old timestamp": 0}
        self._auth = Auth(key) if key else None  # sign and check every message
        self.seen = None
        self._opened = False
        self._watch = ForeignWatch(self.lockstep_checks)  # another sender in this session
        self._sub = self._lc.subscribe(prefix + "STATE", self._on_state)
        self._seq = 0
        self._closed = False
        self.hello(timeout=config.startup_timeout if process else config.give_up_timeout)
        opened = self._control(self._types[2].OPEN, "OPEN (this run's control session)")
        self._watch.opened(opened)
        self._opened = True

    # -- transport ---------------------------------------------------------
    def _publish(self, channel: str, data: bytes) -> None:
        self._lc.publish(channel, self._auth.sign(channel, data) if self._auth else data)

    def _on_state(self, channel: str, data: bytes) -> None:
        if self._auth is not None:
            data, cause = self._auth.verify(channel, data)
            if data is None:
                self.refused[cause] += 1
                return
        msg, _ = decode_state(data)
        if msg is None:  # wrong type, truncated, hostile lengths: counted, not fatal
            self.decode_errors += 1
            self.refused["bad decode"] += 1
        elif self._opened and msg.session != self.session:
            self.refused["other session"] += 1
            self.seen = msg
        else:
            self._watch.on_state(msg, self._seq)
            self._answers.append(msg)

    def foreign_note(self) -> str:
        """What the link saw that was not its plant's answer ('' if nothing)."""
        return foreign_note(self.refused, self.seen, self.last_state)

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    def _plant_exit_message(self) -> str | None:
        return exit_message(self._process, self._stderr_path)

    def _request(self, channel: str, msg, seq: int, timeout: float, what: str,
                 kind: str = "still"):
        data = msg.encode()
        self._publish(channel, data)
        start = time.monotonic()
        last_send = start
        interval = self.config.retry_timeout  # grows by config.backoff per re-send
        resent = 0
        while True:
            now = time.monotonic()
            if now - start > timeout:
                exited = self._plant_exit_message()
                seen = self.foreign_note()
                raise PlantGoneError(
                    f"plant on {self.url} prefix '{self.prefix}' did not answer {what} "
                    f"(seq {seq}) within {timeout:.1f} s after {resent} re-sends"
                    + (f"; {exited}" if exited else "") + (f"; {seen}" if seen else ""))
            wait = max(0.0, min(interval - (now - last_send), timeout - (now - start)))
            try:
                self._lc.handle_timeout(max(1, int(wait * 1000)))
            except OSError:
                # A signal interrupted the wait (lcm reports EINTR as -1): its
                # Python handler runs now, here, where it may raise (SIGINT,
                # a controller's SIGTERM) with the link intact for close().
                # Anything else ends as "did not answer" at the timeout.
                time.sleep(min(wait, 0.005))
            self._watch.check(self.url, self.prefix)  # another sender in this session
            for i, state in enumerate(self._answers):
                # a HELLO is answered in whatever session the plant follows
                if state.command_seq == seq and (state.session == msg.session
                                                 or msg.command == self._types[2].HELLO):
                    del self._answers[:i + 1]  # a real-time plant's later ticks stay queued
                    self._watch.on_answer(self.last_state, state, kind)
                    self.last_state = state
                    self._watch.check(self.url, self.prefix)
                    return state
            self._answers.clear()
            if time.monotonic() - last_send >= interval:
                exited = self._plant_exit_message()
                if exited:
                    raise PlantGoneError(f"plant gone while waiting for {what} (seq {seq}): {exited}")
                self.retries += 1
                resent += 1
                self._publish(channel, data)
                last_send = time.monotonic()
                interval *= self.config.backoff

    def _control(self, command: int, what: str, timeout: float | None = None):
        msg = self._types[2]()
        seq = self._next_seq()
        msg.utime, msg.session, msg.seq, msg.command = time.time_ns() // 1000, self.session, seq, \
            command
        kinds = {msg.RESET: "reset", msg.EVALUATE: "evaluate", msg.START: "start"}
        return self._request(self.prefix + "CONTROL", msg, seq,
                             timeout or self.config.give_up_timeout, what,
                             kinds.get(command, "still"))

    # -- PlantLink ---------------------------------------------------------
    def hello(self, timeout: float | None = None) -> PlantObservation:
        """Handshake: the current state without changing anything."""
        return _from_message(self._control(self._types[2].HELLO, "HELLO", timeout))

    def reset(self) -> PlantObservation:
        return _from_message(self._control(self._types[2].RESET, "RESET"))

    def evaluate(self) -> PlantObservation:
        return _from_message(self._control(self._types[2].EVALUATE, "EVALUATE"))

    def step(self, valves: Sequence[int] | np.ndarray) -> PlantObservation:
        u = valves_array(valves)
        msg = self._types[1]()
        seq = self._next_seq()
        msg.utime, msg.session, msg.seq = time.time_ns() // 1000, self.session, seq
        msg.state_seq = self.last_state.seq if self.last_state is not None else 0
        msg.num_valves = NUM_TANKS
        msg.valve = [int(v) for v in u]
        # (the answer's valves are the applied ones, which a stuck valve makes differ
        # from those sent: they cannot tell a neighbour's command from a fault)
        return _from_message(self._request(self.prefix + "COMMAND", msg, seq,
                                           self.config.give_up_timeout, "valve command", "step"))

    def shutdown(self, timeout: float = 2.0) -> None:
        """Ask the plant process to exit (best effort)."""
        try:
            self._control(self._types[2].SHUTDOWN, "SHUTDOWN", timeout)
        except PlantError:
            pass

    def close(self) -> None:
        """Stop the plant process if this link started it; release LCM."""
        if self._closed:
            return
        self._closed = True
        if self._process is None:  # an attached plant: the next controller may open at once
            try:
                self._control(self._types[2].CLOSE, "CLOSE", 1.0)
            except PlantError:
                pass
        if self._process is not None and self._process.poll() is None:
            self.shutdown(timeout=1.0)
            _stop(self._process)
        self._lc.unsubscribe(self._sub)
        if self._stderr_path:
            try:
                os.unlink(self._stderr_path)
            except OSError:
                pass

    def __enter__(self) -> "LcmPlant":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def process(self):
        return self._process


def _stop(process) -> None:
    """Wait 2 s for a plant asked to shut down, then terminate it, then kill it."""
    try:
        process.wait(timeout=2.0)
    except Exception:  # noqa: BLE001
        process.terminate()
        try:
            process.wait(timeout=2.0)
        except Exception:  # noqa: BLE001
            process.kill()
            process.wait()


def _from_message(msg) -> PlantObservation:
    return PlantObservation(
        level=np.array(msg.level, dtype=np.float64),
        true_level=np.array(msg.true_level, dtype=np.float64),
        valves=np.array(msg.valve, dtype=np.int8),
        deficit=np.array(msg.deficit, dtype=np.float64),
        age=float(msg.age), step=int(msg.step), episode=int(msg.episode),
        operating_steps=int(msg.operating_steps), terminal=bool(msg.terminal),
        truncated=bool(msg.truncated), evaluation=bool(msg.evaluation))


def launch(scenario: str | None = None, seed: int = 0, *, lcm_url: str | None = None,
           prefix: str | None = None, extra_args: Sequence[str] = (),
           config: LinkConfig = LinkConfig(), die_with_caller: bool | None = None,
           link_class: type | None = None, sign: bool = False) -> LcmPlant:
    """Start ``build/plant`` on a private LCM port and prefix; the link owns it.

    die_with_caller: the plant gets SIGKILL when the calling thread ends (so a
        process that is killed or crashes, and never runs close(), leaves no
        plant behind); only for a thread that lives as long as the link. None
        (default): when called from the main thread (PR_SET_PDEATHSIG is per
        thread: from any other thread only close() stops the plant).

    link_class: the link to make (default LcmPlant, the lockstep link; a plant
        launched with ``--mode realtime`` takes ftc.plant.realtime_link.RealtimeLink).

    sign: give the plant a fresh key of its own (in its environment, never on
        its command line) and sign and check every message with it: a process
        without the key can then change nothing.

    Raises PlantError with the plant's own message if it refuses to start
    (e.g. a malformed scenario file).
    """
    url = lcm_url or private_lcm_url()
    prefix = prefix or private_prefix()
    cmd = [str(plant_binary()), "--lcm-url", url, "--prefix", prefix, "--seed", str(int(seed))]
    if scenario:
        cmd += ["--scenario", str(scenario)]
    cmd += list(extra_args)
    stderr = tempfile.NamedTemporaryFile(prefix="ftc-plant-", suffix=".log", delete=False)
    if die_with_caller is None:
        die_with_caller = threading.current_thread() is threading.main_thread()
    preexec = die_with_parent() if die_with_caller else None
    key = new_key() if sign else None
    env = {**os.environ, KEY_VARIABLE: key.hex()} if key else None
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=stderr, preexec_fn=preexec, env=env)
    stderr.close()
    try:
        return (link_class or LcmPlant)(url, prefix, config=config, process=proc,
                                        stderr_path=stderr.name, key=key)
    except PlantGoneError as e:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        exited = None
        try:
            with open(stderr.name, errors="replace") as f:
                exited = f.read().strip()
        except OSError:
            pass
        try:
            os.unlink(stderr.name)
        except OSError:
            pass
        raise PlantError(f"plant failed to start ({' '.join(cmd)}): {exited or e}",
                         exit_code=proc.returncode) from None


def attach(lcm_url: str = DEFAULT_LCM_URL, prefix: str = DEFAULT_PREFIX, timeout: float = 5.0,
           allow_network: bool = False) -> LcmPlant:
    """Drive a plant already running on the bus (started separately with ./build/plant)."""
    return LcmPlant(lcm_url, prefix, config=LinkConfig(give_up_timeout=timeout),
                    allow_network=allow_network)
