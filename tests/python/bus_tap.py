"""A tap on one private plant's bus (its prefix): the states it published and
the commands answering them, as the policy node's tests read them."""

from __future__ import annotations

import threading

import lcm
import numpy as np

from ftc.experiments.processes import with_recv_buffer
from ftc.plant_state_t import plant_state_t
from ftc.valve_command_t import valve_command_t


class BusTap:
    """``states``: seq -> (levels, step, episode); ``answers``: seq -> (the
    valves the plant applied on the step before, the command_seq it answers,
    watchdog_tripped); ``commands``: (state_seq, valves) in the order they were
    sent, ``command_seqs`` their seqs. Listens on a thread until ``stop``."""

    def __init__(self, url: str, prefix: str) -> None:
        # the kernel's default receive buffer holds about 90 datagrams: a tap
        # starved of CPU for half a second at 400 messages per second lost 57 of
        # 240 commands; the recorder's buffer (up to 64 MiB) holds the run
        self.lc = lcm.LCM(with_recv_buffer(url))
        self.states: dict[int, tuple[np.ndarray, int, int]] = {}
        self.answers: dict[int, tuple[np.ndarray, int, bool]] = {}
        self.commands: list[tuple[int, np.ndarray]] = []
        self.command_seqs: list[int] = []
        self.lc.subscribe(prefix + "STATE", self._state)
        self.lc.subscribe(prefix + "COMMAND", self._command)
        self.stop = False
        self.thread = threading.Thread(target=self._spin, daemon=True)
        self.thread.start()

    def _state(self, channel: str, data: bytes) -> None:
        s = plant_state_t.decode(data)
        self.states[s.seq] = (np.array(s.level), s.step, s.episode)
        self.answers[s.seq] = (np.array(s.valve, np.int8), s.command_seq, s.watchdog_tripped)

    def _command(self, channel: str, data: bytes) -> None:
        c = valve_command_t.decode(data)
        self.commands.append((c.state_seq, np.array(c.valve, np.int8)))
        self.command_seqs.append(c.seq)

    def _spin(self) -> None:
        while not self.stop:
            self.lc.handle_timeout(20)
