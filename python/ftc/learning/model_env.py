"""A batched environment on the learned world model, for offline PPO.

The paper trains PPO "offline" on a world model refitted to the degraded
plant's recent data. :class:`ModelEnv` steps ``num_envs`` copies of the plant
as the model sees it, all at once in torch (no Python loop over envs), with
the plant's episode rules (plant-model.md, "Episodes"):

* an episode starts with full tanks (1.0 m);
* it ends (terminal) after a step whose total volume is below one step of
  total engine demand plus 1e-6 m^3;
* it is cut off (truncated) after ``max_episode_steps`` steps, in case the
  model never drains the tanks;
* finished envs are reset at once (auto-reset); the pre-reset observation is
  returned as ``final_obs`` for bootstrapping truncated envs.

The controller is never told the fault parameters, so the engine demand in
the termination rule is estimated from data (:func:`estimate_demand`).
"""

from __future__ import annotations

import numpy as np
import torch

from ftc.common.constants import NUM_TANKS, TANK_HEIGHT, TERMINAL_TOLERANCE
from ftc.learning.rollout import EnvStep
from ftc.learning.transitions import Transitions
from ftc.learning.world_model import WorldModel, torch_threads
from ftc.learning.small_mlp import SmallMLP
from ftc.plant.reward import AREAS, reward, reward_torch

def estimate_demand(data: Transitions, empty_level: float = 1e-3) -> float:
    """Total engine demand per step, m^3, estimated from observed consumption.

    Fuel is conserved by the valves, so the total volume falls over a step by
    exactly what the pumps delivered to the engines. That equals the demand
    unless an engine starves (all tanks on its side empty, or pumps degraded
    below the demand). Over rows where no tank is empty (every level above
    ``empty_level`` m before and after the step) no engine can starve through
    an empty side, so the drop is the demand; the median of those drops is
    robust to sensor noise and to the odd row where an engine starved through
    its degraded pumps. With no such row (a plant that runs its tanks dry
    fast), falls back to the median over rows where the volume fell.

    Pass recent data: under degradation the demand changes with age, and a
    median over several ages returns something in between.
    """
    if len(data) == 0:
        raise ValueError("cannot estimate the demand from no transitions")
    drop = (data.level - data.next_level) @ AREAS
    full = np.all((data.level > empty_level) & (data.next_level > empty_level), axis=1)
    if full.any():
        return float(np.median(drop[full]))
    if (drop > 0).any():
        return float(np.median(drop[drop > 0]))
    raise ValueError("no transition in the data shows any consumption")


class ModelEnv:
    """``num_envs`` plants simulated by a world model, stepped in one batch.

    model:             the world model (its ``predict`` gives the next levels; clipped
                       to [0, 1] m)
    num_envs:          N, envs stepped together
    demand_per_step:   total engine demand over one step, m^3 (from estimate_demand)
    max_episode_steps: steps after which an episode is truncated
    seed:              seed of the env's generator (used by random starts)
    random_start:      start levels uniform in [0.8, 1] m instead of full (the plant's
                       optional extension; off by default, as the plant)
    num_threads:       torch threads while stepping (restored after each step; None:
                       leave as is). One thread is fastest for these small batches.
    engine:            torch: each step in torch; numpy: the same step in NumPy on
                       views of the model's weights (float32 model only), about
                       4x fewer microseconds per step at 16 envs (scripts/bench.py,
                       offline_model_steps_per_s); the reward is computed in
                       float64, so rounding differs from torch's (~1e-7). The
                       PPO's native engine steps with it (offline.py).

    State (read it, or set it in tests): ``level`` (N, 6) m, ``steps`` (N,) steps
    taken in each env's current episode.

    Tensors are float32 on the CPU. Stepping runs under ``torch.no_grad``.
    """

    def __init__(self, model: WorldModel, num_envs: int, demand_per_step: float,
                 max_episode_steps: int = 512, seed: int = 0, *,
                 random_start: bool = False, num_threads: int | None = 1,
                 engine: str = "torch") -> None:
        if engine not in ("torch", "numpy"):
            raise ValueError(f"engine must be torch or numpy, got {engine!r}")
        if num_envs < 1 or max_episode_steps < 1:
            raise ValueError("num_envs and max_episode_steps must be positive")
        if not demand_per_step > 0:
            raise ValueError(f"demand_per_step must be positive, got {demand_per_step}")
        self.model = model
        self.num_envs = int(num_envs)
        self.demand_per_step = float(demand_per_step)
        self.max_episode_steps = int(max_episode_steps)
        self.random_start = random_start
        self.num_threads = num_threads
        self.generator = torch.Generator().manual_seed(int(seed))
        self.dtype = torch.float32
        self.areas = torch.as_tensor(AREAS, dtype=self.dtype)
        self.level = torch.full((self.num_envs, NUM_TANKS), TANK_HEIGHT, dtype=self.dtype)
        self.steps = torch.zeros(self.num_envs, dtype=torch.long)  # steps in the current episode
        self.engine = engine
        if engine == "numpy":
            if any(p.dtype != torch.float32 for p in [*model.parameters(), *model.buffers()]
                   if p.is_floating_point()):
                raise ValueError("ModelEnv(engine='numpy') needs a float32 world model")
            self._tensors = [*model.parameters(), *model.buffers()]
            self._views()

    def _views(self) -> None:
        """NumPy views of the model's current weights and normalisers, and where
        they lie (torch moves a tensor's memory when it is pickled for another
        process: the views are made again then, see :meth:`_step_numpy`)."""
        m = self.model
        self._norm = [b.detach().numpy() for b in (m.in_mean, m.in_std, m.out_mean, m.out_std)]
        self._mlp = SmallMLP(m.net, share=True)
        self._pointers = [t.data_ptr() for t in self._tensors]

    def _start_levels(self, n: int) -> torch.Tensor:
        if self.random_start:
            u = torch.rand((n, NUM_TANKS), generator=self.generator, dtype=self.dtype)
            return TANK_HEIGHT * (0.8 + 0.2 * u)
        return torch.full((n, NUM_TANKS), TANK_HEIGHT, dtype=self.dtype)

    def reset(self) -> torch.Tensor:
        """Start every env afresh; returns the levels, (N, 6) m."""
        self.level = self._start_levels(self.num_envs)
        self.steps.zero_()
        return self.level.clone()

    def step(self, actions: torch.Tensor) -> EnvStep:
        """Apply valves ``actions`` (N, 6) in {0, 1} (any dtype) for one step."""
        if actions.shape != (self.num_envs, NUM_TANKS):
            raise ValueError(f"actions must have shape ({self.num_envs}, {NUM_TANKS}), "
                             f"got {tuple(actions.shape)}")
        if self.engine == "numpy":
            return self._step_numpy(actions)
        with torch.no_grad(), torch_threads(self.num_threads):
            return self._step(actions)

    def _step_numpy(self, actions: torch.Tensor) -> EnvStep:
        """:meth:`_step` in NumPy (the same formulae: WorldModel.predict, the
        reward, the episode rules)."""
        if [t.data_ptr() for t in self._tensors] != self._pointers:
            self._views()
        valves = np.asarray(actions.numpy(), dtype=np.float32)
        level = np.asarray(self.level.numpy(), dtype=np.float32)
        in_mean, in_std, out_mean, out_std = self._norm
        z = (np.concatenate([level, valves], axis=1) - in_mean) / in_std
        nxt = level + (self._mlp.forward(z) * out_std + out_mean)
        np.clip(nxt, 0.0, TANK_HEIGHT, out=nxt)
        r = reward(nxt, valves).astype(np.float32)
        steps = self.steps.numpy()
        steps += 1
        terminal = nxt @ self.areas.numpy() < self.demand_per_step + TERMINAL_TOLERANCE
        truncated = (steps >= self.max_episode_steps) & ~terminal
        done = terminal | truncated
        obs = nxt
        if self.random_start or done.any():  # the torch step draws random starts every step
            obs = np.where(done[:, None], self._start_levels(self.num_envs).numpy(), nxt)
            steps[done] = 0
        self.level = torch.from_numpy(obs.copy())
        return EnvStep(obs=torch.from_numpy(obs.copy()), reward=torch.from_numpy(r),
                       terminal=torch.from_numpy(terminal), truncated=torch.from_numpy(truncated),
                       final_obs=torch.from_numpy(nxt))

    def _step(self, actions: torch.Tensor) -> EnvStep:
        valves = actions.to(self.dtype)
        nxt = self.model.predict(self.level, valves).to(self.dtype)
        r = reward_torch(nxt, valves)
        self.steps += 1
        terminal = nxt @ self.areas < self.demand_per_step + TERMINAL_TOLERANCE
        truncated = (self.steps >= self.max_episode_steps) & ~terminal
        done = terminal | truncated
        obs = torch.where(done.unsqueeze(-1), self._start_levels(self.num_envs), nxt)
        self.steps = torch.where(done, torch.zeros_like(self.steps), self.steps)
        self.level = obs
        return EnvStep(obs=obs.clone(), reward=r, terminal=terminal, truncated=truncated,
                         final_obs=nxt)
