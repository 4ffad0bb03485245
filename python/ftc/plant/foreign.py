"""What shows a lockstep link that another process commands its plant in the
link's own control session (:class:`ForeignWatch`, used by
:class:`ftc.plant.lcm_link.LcmPlant`).

Without a bus key, a neighbour that reads the session id off the bus (every
state carries it) can send commands in it, and the plant cannot tell it from
the controller. The lockstep link then stops (ForeignTrafficError, one line)
at its first request after the plant shows another sender:

* an answer to a seq the link never sent (a neighbour running ahead of it);
* a command of the link's session rejected by the plant (``rejected_commands``:
  a repeat of the seq it applied with other valves, so a neighbour raced the
  link with its next seq; or invalid content; the link sends neither);
* an answer that does not follow from the previous one by the link's request
  alone (:func:`moved_on`: the plant was stepped, reset or started by someone
  else, after a takeover of the session too).
"""

from __future__ import annotations

from ftc.plant.link import ForeignTrafficError


def moved_on(last, new, kind: str) -> str:
    """'' if the plant's answer ``new`` follows from its previous answer ``last`` by
    the link's request ``kind`` alone ("step", "reset", "evaluate", "start",
    "still": a HELLO, OPEN, CLOSE), else what it shows happened in between."""
    over = last.terminal or last.truncated or last.episode < 0
    if kind == "step":
        want = ((last.episode + 1, 1) if over else (last.episode, last.step + 1),
                last.operating_steps + (0 if new.evaluation else 1))
    elif kind in ("reset", "evaluate"):
        want = ((last.episode + 1, 0), last.operating_steps)
    elif kind == "start":
        want = ((last.episode + 1, 0), new.operating_steps)
    else:
        want = ((last.episode, last.step), last.operating_steps)
    got = ((new.episode, new.step), new.operating_steps)
    if got == want:
        return ""
    return (f"after its {kind} the plant is at episode {new.episode} step {new.step}, "
            f"operating step {new.operating_steps}, not episode {want[0][0]} step "
            f"{want[0][1]}, operating step {want[1]}")


class ForeignWatch:
    """The module doc's checks for one link, from the answer to its OPEN on."""

    def __init__(self, enabled: bool = True) -> None:
        self.enabled = enabled  # False: a real-time plant, which steps on its own
        self.found = ""  # what showed another sender ('' : nothing)
        self._rejected0: int | None = None  # the plant's rejected commands at OPEN

    def opened(self, answer) -> None:
        """The answer to the link's OPEN: the checks start."""
        if self.enabled:
            self._rejected0 = int(answer.rejected_commands)

    def on_state(self, msg, last_sent: int) -> None:
        """A state of the link's session arrived; ``last_sent``: its newest seq."""
        if self._rejected0 is not None and not self.found and msg.command_seq > last_sent:
            self.found = (f"the plant answered command seq {msg.command_seq} of this run's "
                          f"session, which this link never sent (its last: {last_sent})")

    def on_answer(self, last, answer, kind: str) -> None:
        """``answer`` answers the link's ``kind`` request; ``last`` its previous answer."""
        if self._rejected0 is None or self.found:
            return
        rejected = int(answer.rejected_commands) - self._rejected0
        if rejected > 0:
            self.found = (f"the plant rejected {rejected} commands of it (a repeat of the seq "
                          "it applied with other valves: another sender raced this link, and "
                          "its valves were applied for that step)")
        elif last is not None:
            self.found = moved_on(last, answer, kind)

    def check(self, url: str, prefix: str) -> None:
        if self.found:
            raise ForeignTrafficError(
                f"foreign traffic in this run's control session on {url} prefix '{prefix}': "
                f"{self.found}; another process holds the session id (a bus key keeps it "
                "out: docs/deploy.md)")
