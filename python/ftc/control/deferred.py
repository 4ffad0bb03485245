"""Learning off the control loop for an agent whose learning is long (the
guided PPO agents' planner-guided fits, 1-3 s), on a real-time plant
(``Agent.background_learning``; docs/deploy.md).

A learning job (the fit after an interval, or a refit within one) runs on a
worker thread. Meanwhile the loop acts with a frozen copy of the policy (its
own random stream) and queues the agent's other calls (``begin_interval``,
``observe``), and a checkpoint gets the agent's state from just before the
job with the job's interval, which a resumed run does again. When the job is
done, between two steps, its metrics go to ``late_metrics`` and the queued
calls are replayed in order (a replayed step's log-probability is the one of
the valves applied, under the policy learned meanwhile). Without
``background_learning`` a job runs at once, in the caller, as before.

A subclass supplies ``_begin_interval``, ``_act``, ``_observe``,
``_end_online``, ``_state_dict``, ``_finish``, ``_close`` and
``acting_policy()``, and runs each long piece of learning through
:meth:`DeferredAgent.learn`.
"""

from __future__ import annotations

import concurrent.futures
import copy
from typing import Any, Callable

import numpy as np
import torch

from ftc.control.agent import Agent, StepContext, Transition
from ftc.plant.link import PlantObservation

PENDING_KEY = "deferred_interval"  # a checkpoint taken while an interval's job ran


class DeferredAgent(Agent):
    """The protocol around a subclass's learning jobs (see the module doc)."""

    _worker: concurrent.futures.ThreadPoolExecutor | None = None
    _job: tuple[concurrent.futures.Future, int | None] | None = None
    _frozen: Any = None
    _saved: dict[str, Any] | None = None

    def __init__(self, seed: int) -> None:
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
        self._saved = {**copy.deepcopy(self._state_dict()), PENDING_KEY: interval}
        self._frozen = copy.deepcopy(self.acting_policy())
        if self._worker is None:
            self._worker = concurrent.futures.ThreadPoolExecutor(1, "guided-fit")
        self._job = (self._worker.submit(job), interval)
        return None

    @property
    def learning(self) -> bool:
        """A job is running (the frozen policy acts)."""
        return self._job is not None

    def _poll(self, wait: bool = False) -> None:
        """Take a finished job (or wait for it) and replay the queued calls, until
        none is left or a replayed call started another job that is running."""
        while self._job is not None:
            future, interval = self._job
            if not (wait or future.done()):
                return
            self._job, self._frozen, self._saved = None, None, None
            metrics = future.result()  # a job's error is raised here, in the loop's thread
            if interval is not None:
                self._late.append((interval, metrics))
            while self._queue and self._job is None:
                method, args = self._queue.pop(0)
                method(*args)

    def _call(self, method: Callable, *args: Any) -> None:
        self._poll()
        if self._job is not None:
            self._queue.append((method, args))
        else:
            method(*args)

    # -- the protocol ------------------------------------------------------------------
    def begin_interval(self, interval: int) -> None:
        self._call(self._begin_interval, interval)

    def act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray:
        self._poll()
        if self._job is None:
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
        if self._worker is not None:
            self._worker.shutdown(wait=True, cancel_futures=True)
            self._worker = None
        self._close()

    def exported_policy(self) -> Any:
        return self._frozen if self._job is not None else self.acting_policy()

    def state_dict(self) -> dict[str, Any]:
        return dict(self._saved) if self._job is not None else self._state_dict()

    # the subclass's halves of the protocol (no-ops where it has nothing to do)
    def _begin_interval(self, interval: int) -> None: pass
    def _act(self, obs: PlantObservation, ctx: StepContext) -> np.ndarray: raise NotImplementedError
    def _observe(self, t: Transition) -> None: pass
    def _end_online(self) -> dict[str, Any]: return {}
    def _state_dict(self) -> dict[str, Any]: return {}
    def _finish(self) -> None: pass
    def _close(self) -> None: pass
