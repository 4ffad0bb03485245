"""The link to a plant in real-time mode (``./build/plant --mode realtime``).

A free-running plant steps at its own rate and publishes one state per tick;
it does not wait. A controller answers each state with one valve command
before the next tick (the plant holds the last command it received), and
opens episodes with control messages, which the plant answers at once:

    START (operating step)  RESET   EVALUATE        -> the new episode's state (step 0)
    tick                    tick    tick   ...      -> one state per plant step

:class:`RealtimeLink` keeps every state in order with its arrival time, so the
caller sees each plant step (also those it was too late to act on) and
measures its latency from a state's arrival to its command's send.
"""

from __future__ import annotations

import time
from typing import Sequence

import numpy as np

from ftc.common.constants import NUM_TANKS
from ftc.plant.lcm_link import LcmPlant, LinkConfig, _from_message
from ftc.plant.link import PlantError, PlantGoneError, PlantObservation, valves_array

# Ticks without a state after which the plant counts as gone (at least
# LinkConfig.give_up_timeout): a real-time plant publishes every tick.
GONE_TICKS = 20
# States LCM keeps for a controller that is late (LCM's default, 30, is 1.5 s
# at 20 Hz: a controller stopped for longer would lose the oldest).
QUEUE_CAPACITY = 100_000
# A state further than this ahead of the newest one is refused: the plant
# publishes one per tick and LCM queues QUEUE_CAPACITY of them, so only a
# forged state jumps so far (one with seq 2**62 would end newest-wins).
MAX_SEQ_JUMP = 1 << 20


class RealtimeLink(LcmPlant):
    """A controller's link to a plant in real-time mode (see the module doc).

    Raises PlantError if the plant answers but runs in lockstep mode."""

    realtime = True
    # the plant steps on its own: the lockstep link's checks of foreign commands do not
    # hold; RealtimeLoop counts them (foreign_commands) instead
    lockstep_checks = False

    def __init__(self, lcm_url: str, prefix: str, *, config: LinkConfig = LinkConfig(),
                 process=None, stderr_path: str | None = None,
                 allow_network: bool = False, key: bytes | None = None) -> None:
        self.arrival_ns: dict[int, int] = {}  # state seq -> time.monotonic_ns() on arrival
        self._last_seq = 0  # newest state handed out
        super().__init__(lcm_url, prefix, config=config, process=process,
                         stderr_path=stderr_path, allow_network=allow_network, key=key)
        self._sub.set_queue_capacity(QUEUE_CAPACITY)
        rate = float(self.last_state.rate_hz)
        if rate <= 0:
            self.close()
            raise PlantError(f"the plant on {lcm_url} prefix '{prefix}' runs in lockstep mode; "
                             "real-time control needs ./build/plant --mode realtime")
        control = self._types[2]
        self.START, self.RESET, self.EVALUATE = control.START, control.RESET, control.EVALUATE
        self.rate_hz = rate
        self.period = 1.0 / rate
        self._gone_after = max(config.give_up_timeout, GONE_TICKS * self.period)
        self._last_seq = self.last_state.seq  # the answer to this link's OPEN

    def _on_state(self, channel: str, data: bytes) -> None:
        before = len(self._answers)
        super()._on_state(channel, data)
        if len(self._answers) > before and len(self.arrival_ns) < QUEUE_CAPACITY:
            self.arrival_ns[self._answers[-1].seq] = time.monotonic_ns()

    def control(self, command: int, operating_step: int = 0):
        """START / RESET / EVALUATE: the plant's answer (the new episode's
        initial state, an LCM message). Ticks that arrive after it are kept
        for :meth:`next_states`."""
        msg = self._types[2]()
        seq = self._next_seq()
        msg.utime, msg.session, msg.seq, msg.command = (time.time_ns() // 1000, self.session,
                                                        seq, command)
        msg.operating_step = int(operating_step)
        names = {msg.START: "START", msg.RESET: "RESET", msg.EVALUATE: "EVALUATE"}
        answer = self._request(self.prefix + "CONTROL", msg, seq, self.config.give_up_timeout,
                               names.get(command, f"control {command}"))
        self._last_seq = answer.seq
        return answer

    def next_states(self) -> list:
        """Every state of this run's session published since the last one
        handed out, oldest first (waits for at least one). A state no newer
        than the last, or implausibly far ahead (MAX_SEQ_JUMP), is counted in
        ``refused`` and ignored: one message cannot end the run or poison
        newest-wins. Raises PlantGoneError, saying what it saw instead, when
        no state of the session comes (the plant stopped, restarted or was
        taken over)."""
        start = time.monotonic()
        while True:
            fresh, newest = [], self._last_seq
            for s in self._answers:
                if newest < s.seq <= newest + MAX_SEQ_JUMP:
                    fresh.append(s)
                    newest = s.seq
                else:
                    self.refused["stale" if s.seq <= newest else "seq jump"] += 1
            self._answers.clear()
            if fresh:
                self._last_seq = fresh[-1].seq
                self.last_state = fresh[-1]
                for seq in [q for q in self.arrival_ns if q < fresh[0].seq]:
                    del self.arrival_ns[seq]
                return fresh
            waited = time.monotonic() - start
            if waited > self._gone_after:
                exited = self._plant_exit_message()
                seen = self.foreign_note()
                raise PlantGoneError(
                    f"plant on {self.url} prefix '{self.prefix}' published no state of this "
                    f"run's session for {waited:.1f} s (it ticks every "
                    f"{self.period * 1000:.0f} ms)" + (f"; {exited}" if exited else "")
                    + (f"; {seen}" if seen else ""))
            try:
                self._lc.handle_timeout(max(1, int(1000 * min(self.period, self._gone_after))))
            except OSError:  # a signal interrupted the wait: its handler has run
                pass
            while self._lc.handle_timeout(0) > 0:  # take everything queued
                pass

    def send(self, valves: Sequence[int] | np.ndarray, state_seq: int) -> int:
        """Publish the command answering state ``state_seq``; returns its seq."""
        msg = self._types[1]()
        msg.seq = self._next_seq()
        msg.utime, msg.session = time.time_ns() // 1000, self.session
        msg.state_seq = int(state_seq)
        msg.num_valves = NUM_TANKS
        msg.valve = [int(v) for v in valves_array(valves)]
        self._publish(self.prefix + "COMMAND", msg.encode())
        return msg.seq

    def step(self, valves):  # the lockstep protocol does not apply
        raise PlantError("a real-time plant is not stepped on request: use send() and "
                         "next_states()")


def observation(msg) -> PlantObservation:
    """The observation a state message carries."""
    return _from_message(msg)
