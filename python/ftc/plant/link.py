"""Talking to the plant: the observation type, the link protocol every
controller uses, and two links: the real plant process over LCM
(:class:`LcmPlant`, lockstep with sequence checks and retries) and the same
C++ core in process (:class:`CorePlant`, for simulation and tests).
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass
from typing import Protocol, Sequence

import numpy as np

NUM_TANKS = 6
NUM_ENGINES = 2


@dataclass(frozen=True)
class PlantObservation:
    """What the plant reports after a reset or a step.

    level:       (6,) published levels, m (sensor noise included if enabled)
    true_level:  (6,) noise-free levels, m (logging and validation only)
    valves:      (6,) int valves applied during the step (zeros after a reset)
    deficit:     (2,) unmet engine demand over the step, m^3
    age:         degradation age in force during the step, intervals
    step:        steps taken in the episode (0 after a reset)
    episode:     episode counter since the plant started
    operating_steps: steps counted towards degradation so far
    terminal:    fuel exhausted (do not bootstrap)
    truncated:   cut off at an interval boundary (bootstrap)
    evaluation:  an evaluation episode (age frozen, steps not counted)
    """

    level: np.ndarray
    true_level: np.ndarray
    valves: np.ndarray
    deficit: np.ndarray
    age: float
    step: int
    episode: int
    operating_steps: int
    terminal: bool
    truncated: bool
    evaluation: bool

    @property
    def done(self) -> bool:
        return self.terminal or self.truncated


class PlantLink(Protocol):
    """The interface every controller drives a plant through."""

    def reset(self) -> PlantObservation:
        """Start a new operating episode from full tanks at the current age."""

    def evaluate(self) -> PlantObservation:
        """Start an evaluation episode (age frozen at the last operating step's)."""

    def step(self, valves: Sequence[int] | np.ndarray) -> PlantObservation:
        """Apply valves (6 ints in {0, 1}) for one 1 s control step."""

    def close(self) -> None:
        """Release the link (and stop the plant process if this link owns it)."""


def _valves_array(valves: Sequence[int] | np.ndarray) -> np.ndarray:
    u = np.asarray(valves)
    if u.shape != (NUM_TANKS,):
        raise ValueError(f"valves must have shape ({NUM_TANKS},), got {u.shape}")
    if not np.all((u == 0) | (u == 1)):
        raise ValueError(f"valves must be 0 or 1, got {u.tolist()}")
    return u.astype(np.int8)


class CorePlant:
    """The C++ plant core in this process (no LCM): same physics, same episodes.

    Used for nominal pretraining in simulation and as the reference the LCM
    plant is checked against.
    """

    def __init__(self, scenario: str | None = None, seed: int = 0, *,
                 steps_per_interval: int | None = None, start_step: int = 0) -> None:
        from ftc import _core  # built by CMake into build/python

        self._core = _core
        self.scenario = _core.load_scenario(str(scenario)) if scenario else _core.Scenario()
        if steps_per_interval is not None:
            self.scenario.steps_per_interval = int(steps_per_interval)
        self._plant = _core.Plant(self.scenario, int(seed))
        if start_step:
            self._plant.set_operating_steps(int(start_step))

    def _observation(self, d: dict) -> PlantObservation:
        return PlantObservation(
            level=np.array(d["observed"], dtype=np.float64),
            true_level=np.array(d["level"], dtype=np.float64),
            valves=np.array(d["valves"], dtype=np.int8),
            deficit=np.array(d["deficit"], dtype=np.float64),
            age=float(d["age"]), step=int(d["step"]), episode=int(d["episode"]),
            operating_steps=int(self._plant.operating_steps),
            terminal=bool(d["terminal"]), truncated=bool(d["truncated"]),
            evaluation=bool(d["evaluation"]))

    def reset(self) -> PlantObservation:
        self._plant.reset()
        return self._observation(self._plant.last())

    def evaluate(self) -> PlantObservation:
        self._plant.reset_evaluation()
        return self._observation(self._plant.last())

    def step(self, valves: Sequence[int] | np.ndarray) -> PlantObservation:
        return self._observation(self._plant.step(_valves_array(valves).tolist()))

    def close(self) -> None:
        pass


# --------------------------------------------------------------------------
# The real plant process over LCM
# --------------------------------------------------------------------------

DEFAULT_LCM_URL = "udpm://239.255.76.67:7667?ttl=0"
DEFAULT_PREFIX = "FTC_"


class PlantError(RuntimeError):
    """The plant link failed (plant gone, refused to start, or answered nonsense).

    exit_code: the plant process's exit code when it exited (2: bad input).
    """

    def __init__(self, message: str, exit_code: int | None = None) -> None:
        super().__init__(message)
        self.exit_code = exit_code


class PlantGoneError(PlantError):
    """The plant stopped answering (killed, crashed, or not there)."""


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


def private_lcm_url(port: int | None = None) -> str:
    """A loopback-only multicast URL on a random (or given) port, for one run."""
    import random

    port = port if port is not None else random.SystemRandom().randrange(20000, 60000)
    return f"udpm://239.255.76.67:{port}?ttl=0"


def private_prefix() -> str:
    """A channel prefix unique to this process and call."""
    import os
    import secrets

    return f"FTC{os.getpid()}_{secrets.token_hex(3)}_"


def check_loopback_url(url: str, allow_network: bool = False) -> None:
    """Refuse an LCM URL that may leave this machine unless asked for explicitly."""
    import warnings

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


class LcmPlant:
    """Lockstep link to a plant process over LCM (implements :class:`PlantLink`).

    Every request carries a fresh sequence number (starting from the wall clock
    in microseconds, so a later client always outranks an earlier one); the
    plant's answer carries it back. Answers to other sequence numbers are
    ignored. A request not answered within ``retry_timeout`` is re-sent with the
    same seq (the plant answers a repeat without stepping twice); after
    ``give_up_timeout`` without an answer, :class:`PlantGoneError` is raised.
    """

    def __init__(self, lcm_url: str, prefix: str, *, config: LinkConfig = LinkConfig(),
                 process: "subprocess.Popen | None" = None, stderr_path: str | None = None,
                 allow_network: bool = False) -> None:
        import time

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
        self._sub = self._lc.subscribe(prefix + "STATE", self._on_state)
        self._seq = time.time_ns() // 1000
        self._closed = False
        self.hello(timeout=config.startup_timeout if process else config.give_up_timeout)

    # -- transport ---------------------------------------------------------
    def _on_state(self, channel: str, data: bytes) -> None:
        try:
            self._answers.append(self._types[0].decode(data))
        except (ValueError, struct.error):  # wrong fingerprint / truncated: counted, not fatal
            self.decode_errors += 1

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    def _plant_exit_message(self) -> str | None:
        if self._process is None or self._process.poll() is None:
            return None
        tail = ""
        if self._stderr_path:
            try:
                with open(self._stderr_path, errors="replace") as f:
                    tail = f.read()[-2000:].strip()
            except OSError:
                pass
        return (f"plant process exited with code {self._process.returncode}"
                + (f": {tail}" if tail else ""))

    def _request(self, channel: str, msg, seq: int, timeout: float, what: str):
        import time

        data = msg.encode()
        self._lc.publish(channel, data)
        start = time.monotonic()
        last_send = start
        interval = self.config.retry_timeout  # grows by config.backoff per re-send
        resent = 0
        while True:
            now = time.monotonic()
            if now - start > timeout:
                exited = self._plant_exit_message()
                raise PlantGoneError(
                    f"plant on {self.url} prefix '{self.prefix}' did not answer {what} "
                    f"(seq {seq}) within {timeout:.1f} s after {resent} re-sends"
                    + (f"; {exited}" if exited else ""))
            wait = max(0.0, min(interval - (now - last_send), timeout - (now - start)))
            self._lc.handle_timeout(max(1, int(wait * 1000)))
            for state in self._answers:
                if state.command_seq == seq:
                    self._answers.clear()
                    self.last_state = state
                    return state
            self._answers.clear()
            if time.monotonic() - last_send >= interval:
                exited = self._plant_exit_message()
                if exited:
                    raise PlantGoneError(f"plant gone while waiting for {what} (seq {seq}): {exited}")
                self.retries += 1
                resent += 1
                self._lc.publish(channel, data)
                last_send = time.monotonic()
                interval *= self.config.backoff

    def _control(self, command: int, what: str, timeout: float | None = None):
        msg = self._types[2]()
        seq = self._next_seq()
        msg.utime, msg.seq, msg.command = self._seq, seq, command
        return self._request(self.prefix + "CONTROL", msg, seq,
                             timeout or self.config.give_up_timeout, what)

    # -- PlantLink ---------------------------------------------------------
    def hello(self, timeout: float | None = None) -> PlantObservation:
        """Handshake: the current state without changing anything."""
        return _from_message(self._control(self._types[2].HELLO, "HELLO", timeout))

    def reset(self) -> PlantObservation:
        return _from_message(self._control(self._types[2].RESET, "RESET"))

    def evaluate(self) -> PlantObservation:
        return _from_message(self._control(self._types[2].EVALUATE, "EVALUATE"))

    def step(self, valves: Sequence[int] | np.ndarray) -> PlantObservation:
        import time

        u = _valves_array(valves)
        msg = self._types[1]()
        seq = self._next_seq()
        msg.utime = time.time_ns() // 1000
        msg.seq = seq
        msg.state_seq = self.last_state.seq if self.last_state is not None else 0
        msg.num_valves = NUM_TANKS
        msg.valve = [int(v) for v in u]
        return _from_message(self._request(self.prefix + "COMMAND", msg, seq,
                                           self.config.give_up_timeout, "valve command"))

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
        if self._process is not None:
            if self._process.poll() is None:
                self.shutdown(timeout=1.0)
                try:
                    self._process.wait(timeout=2.0)
                except Exception:  # noqa: BLE001
                    self._process.terminate()
                    try:
                        self._process.wait(timeout=2.0)
                    except Exception:  # noqa: BLE001
                        self._process.kill()
                        self._process.wait()
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
           config: LinkConfig = LinkConfig()) -> LcmPlant:
    """Start ``build/plant`` on a private LCM port and prefix; the link owns it.

    Raises PlantError with the plant's own message if it refuses to start
    (e.g. a malformed scenario file).
    """
    import subprocess
    import tempfile

    from ftc.build_info import plant_binary

    url = lcm_url or private_lcm_url()
    prefix = prefix or private_prefix()
    cmd = [str(plant_binary()), "--lcm-url", url, "--prefix", prefix, "--seed", str(int(seed))]
    if scenario:
        cmd += ["--scenario", str(scenario)]
    cmd += list(extra_args)
    stderr = tempfile.NamedTemporaryFile(prefix="ftc-plant-", suffix=".log", delete=False)
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=stderr)
    stderr.close()
    try:
        return LcmPlant(url, prefix, config=config, process=proc, stderr_path=stderr.name)
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
