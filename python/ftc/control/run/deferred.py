"""Learning off the control loop for an agent whose learning is long (the
guided PPO agents' planner-guided fits, 1-3 s), on a real-time plant
(``Agent.background_learning``; docs/deploy.md).

A learning job (the fit after an interval, or a refit within one) runs on a
worker thread. Meanwhile the loop acts with a frozen copy of the policy (its
own random stream) and queues the agent's other calls (``begin_interval``,
``observe``). When the job is done, between two steps, its metrics go to
``late_metrics``, ``on_learned`` is called (set by the runner: the agent's
state is then the one after the interval the fit ended, and the runner saves
that interval's checkpoint), and the queued calls are replayed in order (a
replayed step's log-probability is the one of the valves applied, under the
policy learned meanwhile). Without ``background_learning`` a job runs at
once, in the caller, as before.

A subclass supplies ``_begin_interval``, ``_act``, ``_observe``,
``_end_online``, ``_state_dict``, ``_finish``, ``_close`` and
``acting_policy()``, and runs each long piece of learning through
:meth:`DeferredAgent.learn`.
"""

from __future__ import annotations

import copy
from typing import Any, Callable

import numpy as np
import torch

from ftc.control.run.agent import Agent, StepContext, Transition
from ftc.control.run.background import OneJob
from ftc.plant.link import PlantObservation


class DeferredAgent(Agent):
    """The protocol around a subclass's learning jobs (see the module doc)."""

    _frozen: Any = None
    on_learned: Callable[[int], None] | None = None

    def __init__(self, seed: int) -> None:
        self._jobs = OneJob("guided-fit")
        self._queue: list[tuple[Callable, tuple]] = []
        self._late: list[tuple[int, dict[str, Any]]] = []
        self._acting_generator = torch.Generator().manual_seed(seed)

    # -- the subclass's side -------------------------------------------------------
    def acting_policy(self) -> Any:
        raise NotImplementedError

    def learn(self, job: Callable[[], dict[str, Any]], interval: int | None = None
              ) -> dict[str, Any] | None:
        """Run ``job``: at once, returning its metrics; or, with background
        learning, on the worker (None now; an interval's metrics come late)."""
        if not self.background_learning:
            return job()
        self._frozen = copy.deepcopy(self.acting_policy())
        self._jobs.submit(job, interval)
        return None

    @property
    def learning(self) -> bool:
        """A job is running (the frozen policy acts)."""
        return self._jobs.running

    def _poll(self, wait: bool = False) -> None:
        """Take a finished job (or wait for it) and replay the queued calls, until
        none is left or a replayed call started another job that is running."""
        while (done := self._jobs.take(wait)) is not None:
            self._frozen = None
            metrics, interval = done  # a job's error was raised, in the loop's thread
            if interval is not None:
                self._late.append((interval, metrics))
                if self.on_learned is not None:
                    self.on_learned(interval)
            while self._queue and not self._jobs.running:
                method, args = self._queue.pop(0)
                method(*args)

    def _call(self, method: Callable, *args: Any) -> None:
        self._poll()
        if self._jobs.running:
            self._queue.append((method, args))
        else:
            method(*args)

    # -- the protocol ------------------------------------------------------------------
    def begin_interval(self, interval: int) -> None:
        self._call(self._begin_interval, interval)

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        self._poll()
        if not self._jobs.running:
            return self._act(obs, ctx)
        x = torch.as_tensor(obs.level, dtype=torch.float32).unsqueeze(0)
        actions, _, _ = self._frozen.act(x, self._acting_generator, ctx.evaluation)
        return actions[0].numpy().astype(np.int8)

    def observe(self, t: Transition) -> None:
        self._call(self._observe, t)

    def end_online(self) -> dict[str, Any]:
        self._poll(wait=True)  # the interval's steps all learned from
        return self._end_online()

    def late_metrics(self) -> list[tuple[int, dict[str, Any]]]:
        self._poll()
        late, self._late = self._late, []
        return late

    def finish(self) -> None:
        self._poll(wait=True)
        self._finish()

    def close(self) -> None:
        self._jobs.close()
        self._close()

    def exported_policy(self) -> Any:
        return self._frozen if self._jobs.running else self.acting_policy()

    def state_dict(self) -> dict[str, Any]:
        if self._jobs.running:  # the runner saves from on_learned instead
            raise RuntimeError("the agent's state is changing: a fit is running")
        return self._state_dict()

    # the subclass's halves of the protocol (no-ops where it has nothing to do)
    def _begin_interval(self, interval: int) -> None: pass
    def _act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray: raise NotImplementedError
    def _observe(self, t: Transition) -> None: pass
    def _end_online(self) -> dict[str, Any]: return {}
    def _state_dict(self) -> dict[str, Any]: return {}
    def _finish(self) -> None: pass
    def _close(self) -> None: pass
