"""Distillation with DAgger: the adaptive student learns oracle-mpc's decisions
on its own state distribution, over plants drawn from the training
distribution (docs/adaptive.md).

Iteration k (of ``iterations``):

1. ``envs`` plants drawn from the distribution (seed ``seed * 1000 + k``,
   ``distribution.draw_seed``) in the batched pool (``ftc.plant.vector``,
   same-step autoreset), each run for
   its whole life (``life_intervals`` x 512 steps, ageing as a plant does);
2. at every step, env i is driven by the teacher if i < beta_k * envs (beta
   halves each iteration from 1: iteration 0 is the teacher's own rollouts),
   else by the student; the teacher labels every state it drives and a
   fraction ``label_fraction`` of the student's (DAgger: the states the
   student itself reaches, its mistakes included);
3. the labelled (history window, teacher valves, regret of every setting)
   samples join the data set (the newest ``max_samples`` kept), and the
   student is trained on it for ``epochs`` epochs: with the joint head, cross
   entropy of the teacher's setting plus ``regret`` times the student's
   expected regret; with the valves head, binary cross-entropy on each valve.
   With ``privileged`` > 0, a second head on the student's last hidden layer
   learns what the teacher knows and the student is not told, which valves
   are stuck closed and which stuck open at that step (:func:`stuck_valves`),
   its binary cross-entropy weighted by ``privileged`` and added: the hidden
   layer must then carry the evidence of a stuck valve in the window (Rapid
   Motor Adaptation's student regresses the true parameters' latent the same
   way). With ``privileged_params`` > 0, another head regresses the true
   degraded parameters in force at that step (:func:`true_parameters`: each
   pump's capacity, each tank's outflow conductance and each engine's demand,
   as fractions of their healthy values), its squared error (summed over the
   14) weighted by ``privileged_params`` and added: Rapid Motor Adaptation's
   latent of the parameters, here the parameters themselves. The heads are
   used in training only; the checkpoint's network is the policy alone.

Every iteration's student is kept (the learning curve evaluates them); the
last one is the checkpoint. With ``members`` > 1 the students of seeds seed,
seed + 1, ... are trained one after another and the checkpoint is their
ensemble. Torch runs on one thread.
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
import torch

from ftc.common.constants import NUM_ENGINES, NUM_TANKS
from ftc.common.lifetime import tie_to
from ftc.control.planning.physics.teacher import PoolTeacher
from ftc.experiments.adaptive.distribution import TrainingDistribution, draw, draw_seed
from ftc.learning.history_policy import (HistoryPolicy, HistoryWindow, TrainingConfig, ensemble,
                                         rates_map)
from ftc.plant.vector import FuelTransferVectorEnv


STUCK_TARGETS = 2 * NUM_TANKS  # per valve: stuck closed, then per valve: stuck open
# per tank: pump capacity, then per tank: outflow conductance, then per engine: demand
PARAM_TARGETS = 2 * NUM_TANKS + NUM_ENGINES
_HEALTHY: dict[str, np.ndarray] = {}  # the healthy plant's parameters, read once


def stuck_valves(events: list[dict], operating_step: int) -> np.ndarray:
    """The privileged head's targets for a plant at ``operating_step`` of its
    life: (12,) float32, entry v - 1 set when valve v is stuck closed, entry
    6 + v - 1 when it is stuck open (its stuck-valve event at that step or
    before; a later event on the same valve overrides an earlier one)."""
    state: dict[int, str] = {}
    for e in sorted(events, key=lambda e: e["at_step"]):
        if "stuck_valve" in e and e["at_step"] <= operating_step:
            state[int(e["stuck_valve"])] = e["state"]
    out = np.zeros(STUCK_TARGETS, np.float32)
    for valve, how in state.items():
        out[valve - 1 + (NUM_TANKS if how == "open" else 0)] = 1.0
    return out


def true_parameters(scenario: Any, operating_step: int) -> np.ndarray:
    """The parameter head's targets for a plant of ``scenario`` at
    ``operating_step`` of its life: (14,) float32, the parameters in force at
    that step (its age and the events applied, as the teacher plans with) as
    fractions of the healthy plant's, each in [0, 1] with 1 healthy: the
    pumps' capacity (pump rate over the healthy one; 0 for a dead pump), then
    the tanks' outflow conductance (healthy resistance over the resistance),
    then the engines' healthy demand over their demand (falling as an engine
    burns more)."""
    from ftc import _core  # native: the C++ degradation, as the plant applies it

    if not _HEALTHY:
        _HEALTHY.update(_core.params_at_step(_core.Scenario(), 0))
    p = _core.params_at_step(scenario, int(operating_step))
    out = np.concatenate([np.asarray(p["pump"]) / _HEALTHY["pump"],
                          _HEALTHY["resistance"] / np.asarray(p["resistance"]),
                          _HEALTHY["demand"] / np.asarray(p["demand"])])
    return np.clip(out, 0.0, 1.0).astype(np.float32)


@dataclass
class Dataset:
    """Labelled samples, the newest ``capacity`` kept: features (M, F) float32,
    valves (M, 6) int8, the teacher's regrets (M, 64) float32 (empty (M, 0)
    when they are not kept), the privileged head's targets (M, 12) float32
    (:func:`stuck_valves`) and the parameter head's (M, 14) float32
    (:func:`true_parameters`), each empty (M, 0) when they are not kept."""

    capacity: int
    features: list[np.ndarray] = field(default_factory=list)
    valves: list[np.ndarray] = field(default_factory=list)
    regrets: list[np.ndarray] = field(default_factory=list)
    stuck: list[np.ndarray] = field(default_factory=list)
    params: list[np.ndarray] = field(default_factory=list)

    def add(self, x: np.ndarray, y: np.ndarray, regrets: np.ndarray | None = None,
            stuck: np.ndarray | None = None, params: np.ndarray | None = None) -> None:
        none = np.zeros((len(x), 0), np.float32)
        for kept, a in ((self.features, x), (self.valves, y), (self.regrets, regrets),
                        (self.stuck, stuck), (self.params, params)):
            kept.append(none if a is None else a)
        while sum(len(a) for a in self.features) - len(self.features[0]) >= self.capacity:
            for kept in (self.features, self.valves, self.regrets, self.stuck, self.params):
                kept.pop(0)

    def arrays(self) -> tuple[np.ndarray, ...]:
        """(features, valves, regrets, stuck, params), the newest ``capacity``."""
        return tuple(np.concatenate(a)[-self.capacity:] for a in (
            self.features, self.valves, self.regrets, self.stuck, self.params))


def collect(policy: HistoryPolicy, teacher: PoolTeacher, dist: TrainingDistribution,
            config: TrainingConfig, iteration: int, beta: float) -> dict[str, Any]:
    """One iteration's rollouts: (features, teacher valves) and statistics."""
    rng = np.random.default_rng([config.seed, iteration, 1])
    scenarios = draw(dist, config.envs, draw_seed(config.seed, iteration))
    env = FuelTransferVectorEnv(config.envs, scenarios, plant_seed=config.seed * 10**6 +
                                iteration * config.envs, autoreset="same_step", threads=1,
                                copy=False)
    teacher.forget()
    obs, _ = env.reset()
    window = HistoryWindow(config.envs, config.window, config.stuck_memory)
    window.start(obs)
    driven = np.arange(config.envs) < round(beta * config.envs)  # by the teacher
    perturb = Perturbation(config, iteration, ~driven) if config.explore > 0 else None
    xs, ys, gs, zs, ps, reward, student_reward = [], [], [], [], [], 0.0, []
    keep_regrets = config.head == "joint"
    events = [s.events for s in scenarios]  # a property that copies: read once
    steps = config.life_intervals * dist.steps_per_interval
    for _ in range(steps):
        features = window.features()
        u = policy.act(features)
        labelled = driven | (rng.random(config.envs) < config.label_fraction)
        envs = np.flatnonzero(labelled)
        if len(envs):
            ops = np.array([env.pool.operating_steps(int(i)) for i in envs])
            seen = window.stuck[envs] if config.teacher_stuck == "seen" else None
            labels, regrets = teacher.label_with_regrets(envs, scenarios, ops, obs[envs], seen)
            xs.append(features[envs])
            ys.append(labels)
            if keep_regrets:
                gs.append(regrets)
            if config.privileged > 0:
                zs.append(np.stack([stuck_valves(events[i], op) for i, op in zip(envs, ops)]))
            if config.privileged_params > 0:
                ps.append(np.stack([true_parameters(scenarios[i], op)
                                    for i, op in zip(envs, ops)]))
            u[driven] = labels[driven[envs]]
        if perturb is not None:
            perturb.apply(u)
        obs, r, terminated, truncated, info = env.step(u)
        reward += float(r.mean())
        if (~driven).any():
            student_reward.append(float(r[~driven].mean()))
        window.push(obs, u, terminated | truncated, info["valves"])
        if perturb is not None:
            perturb.end(terminated | truncated)
    env.close()
    return {"x": np.concatenate(xs), "y": np.concatenate(ys),
            "regrets": np.concatenate(gs) if keep_regrets else None,
            "stuck": np.concatenate(zs) if zs else None,
            "params": np.concatenate(ps) if ps else None, "steps": steps * config.envs,
            "reward_per_step": reward / steps,
            "student_reward_per_step": float(np.mean(student_reward)) if student_reward else None,
            "perturbed": perturb.steps / (steps * config.envs) if perturb is not None else None}


class Perturbation:
    """TrainingConfig.explore's noise: in the plants ``eligible`` (those the
    student drives), each step not yet perturbed begins a perturbation with
    chance ``explore``: a random valve setting held for 1 to ``explore_hold``
    steps (uniform) in place of the commands. Its own random stream, so that
    ``explore`` 0 leaves every other draw as it was."""

    def __init__(self, config: TrainingConfig, iteration: int, eligible: np.ndarray) -> None:
        self.rng = np.random.default_rng([config.seed, iteration, 2])
        self.chance, self.longest, self.eligible = config.explore, config.explore_hold, eligible
        self.setting = np.zeros((len(eligible), NUM_TANKS), np.int8)
        self.left = np.zeros(len(eligible), np.int64)  # steps the perturbation still holds
        self.steps = 0  # perturbed steps, all plants

    def apply(self, u: np.ndarray) -> None:
        """Replaces the commands ``u`` (N, 6) of the perturbed plants, in place."""
        start = self.eligible & (self.left == 0) & (self.rng.random(len(u)) < self.chance)
        n = int(start.sum())
        if n:
            self.setting[start] = self.rng.integers(0, 2, size=(n, NUM_TANKS), dtype=np.int8)
            self.left[start] = self.rng.integers(1, self.longest + 1, size=n)
        on = self.left > 0
        u[on] = self.setting[on]
        self.left[on] -= 1
        self.steps += int(on.sum())

    def end(self, done: np.ndarray) -> None:
        """Plants whose episode ended start the next one unperturbed."""
        self.left[done] = 0


def settings_of(valves: np.ndarray) -> np.ndarray:
    """Setting index a (valve i open iff bit i of a) of valves (N, 6)."""
    return (np.asarray(valves, np.int64) << np.arange(valves.shape[1])).sum(axis=1)


def loss_of(policy: HistoryPolicy, x: torch.Tensor, y: torch.Tensor, a: torch.Tensor,
            g: torch.Tensor, config: TrainingConfig, regret_scale: float,
            head: torch.nn.Module | None = None, z: torch.Tensor | None = None,
            param_head: torch.nn.Module | None = None, theta: torch.Tensor | None = None
            ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """The student's loss on a minibatch: BCE per valve (valves head), or the
    cross entropy of the teacher's setting plus ``config.regret`` times the
    expected regret per unit of ``regret_scale`` (joint head); with the
    privileged ``head`` and its targets ``z``, plus ``config.privileged``
    times that head's BCE; with the ``param_head`` and its targets ``theta``,
    plus ``config.privileged_params`` times its squared error (summed over
    the parameters, mean over the samples). Returns the loss, the privileged
    BCE and the parameters' error (each None where its head is not
    trained)."""
    hidden = policy.trunk(x)
    logits = policy.net[-1](hidden)
    if config.head == "valves":
        loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, y)
    else:
        loss = torch.nn.functional.cross_entropy(logits, a)
        if config.regret > 0:
            p = torch.softmax(logits, dim=1)
            loss = loss + config.regret * (p * g).sum(dim=1).mean() / regret_scale
    stuck = mse = None
    if head is not None and z is not None:
        stuck = torch.nn.functional.binary_cross_entropy_with_logits(head(hidden), z)
        loss = loss + config.privileged * stuck
    if param_head is not None and theta is not None:
        # summed over the 14 parameters, so that one worn part weighs as much
        # however many stay healthy; mean over the samples
        mse = ((param_head(hidden) - theta) ** 2).sum(dim=1).mean()
        loss = loss + config.privileged_params * mse
    return loss, stuck, mse


def fit(policy: HistoryPolicy, optimizer: torch.optim.Optimizer, x: np.ndarray, y: np.ndarray,
        config: TrainingConfig, rng: np.random.Generator, regrets: np.ndarray | None = None,
        head: torch.nn.Module | None = None, stuck: np.ndarray | None = None,
        param_head: torch.nn.Module | None = None, params: np.ndarray | None = None
        ) -> dict[str, float]:
    """``epochs`` epochs of minibatches on (x, y, regrets (M, 64) or None), with
    the privileged ``head`` on its targets ``stuck`` (M, 12) and the
    ``param_head`` on its targets ``params`` (M, 14) if given (:func:`loss_of`;
    ``optimizer`` must hold the heads' parameters too); the last epoch's
    loss, the fraction of samples where the student's valves are the
    teacher's (all six), its mean regret where the regrets are given, and
    each head's last-epoch loss where it is trained."""
    if regrets is None:
        regrets = np.zeros((len(x), 0), np.float32)
    xt, yt = torch.as_tensor(x), torch.as_tensor(y, dtype=torch.float32)
    at = torch.as_tensor(settings_of(y))
    gt = torch.as_tensor(regrets)
    zt = torch.as_tensor(stuck) if head is not None and stuck is not None else None
    pt = (torch.as_tensor(params) if param_head is not None and params is not None
          else None)
    scale = float(regrets.mean()) if regrets.size and regrets.mean() > 0 else 1.0
    policy.train()
    losses: list[float] = []
    stuck_losses: list[float] = []
    param_losses: list[float] = []
    for _ in range(config.epochs):
        losses, stuck_losses, param_losses = [], [], []
        order = torch.as_tensor(rng.permutation(len(x)))
        for start in range(0, len(x), config.batch):
            idx = order[start:start + config.batch]
            loss, stuck_loss, param_loss = loss_of(
                policy, xt[idx], yt[idx], at[idx], gt[idx] if regrets.size else gt, config,
                scale, head, zt[idx] if zt is not None else None, param_head,
                pt[idx] if pt is not None else None)
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
            losses.append(loss.item())
            if stuck_loss is not None:
                stuck_losses.append(stuck_loss.item())
            if param_loss is not None:
                param_losses.append(param_loss.item())
    policy.eval()
    u = policy.act(x)
    out = {"loss": float(np.mean(losses)),
           "action_agreement": float((u == y).all(axis=1).mean())}
    if regrets.size:
        out["mean_regret"] = float(regrets[np.arange(len(x)), settings_of(u)].mean())
    if stuck_losses:
        out["stuck_bce"] = float(np.mean(stuck_losses))
    if param_losses:
        out["params_mse"] = float(np.mean(param_losses))
    return out


def train(dist: TrainingDistribution, config: TrainingConfig,
          log: Callable[[str], None] = print, jobs: int = 1) -> dict[str, Any]:
    """The student after ``config.iterations`` DAgger iterations: a record with its
    weights (``policy``), every iteration's weights (``snapshots``) and the
    curve (``curve``: per iteration, env steps, teacher labels, wall seconds,
    loss, agreement, rewards). ``jobs`` > 1 trains that many members at once,
    each in a process of its own (the same weights as one after another), whose
    lines go to stdout named by member rather than to ``log``; a member that
    fails (or Ctrl-C) stops the others."""
    if config.life_intervals > dist.life_intervals:
        raise ValueError(f"life_intervals {config.life_intervals} exceeds the distribution's "
                         f"{dist.life_intervals} (its events are drawn within it)")
    if jobs < 1:
        raise ValueError(f"jobs must be >= 1, got {jobs}")
    if config.members > 1:
        return _train_members(dist, config, log, jobs)
    torch.set_num_threads(1)
    torch.manual_seed(config.seed)
    rng = np.random.default_rng([config.seed, 2])
    policy = HistoryPolicy(config.student())
    policy.eval()
    # the privileged head (training only: not in the checkpoint), drawn after the policy
    head = (torch.nn.Linear(config.hidden[-1], STUCK_TARGETS) if config.privileged > 0
            else None)
    # the parameter head (training only), drawn after them: a student without
    # it starts from the same weights as before it existed
    param_head = (torch.nn.Linear(config.hidden[-1], PARAM_TARGETS)
                  if config.privileged_params > 0 else None)
    weights = [*policy.parameters()] + [w for h in (head, param_head) if h is not None
                                        for w in h.parameters()]
    optimizer = torch.optim.Adam(weights, lr=config.lr)
    teacher = PoolTeacher.from_config(config)
    data = Dataset(config.max_samples)
    start, steps = time.monotonic(), 0
    curve, snapshots = [], []
    for k in range(config.iterations):
        beta = 1.0 if not config.dagger else 0.5 ** k
        rollouts = collect(policy, teacher, dist, config, k, beta)
        steps += rollouts["steps"]
        data.add(rollouts["x"], rollouts["y"], rollouts["regrets"], rollouts["stuck"],
                 rollouts["params"])
        x, y, g, z, p = data.arrays()
        if config.inputs == "rates" and policy.input_map is None:
            policy.set_input_map(*rates_map(config.window, x))  # fixed from iteration 0's data
        stats = fit(policy, optimizer, x, y, config, rng, g, head, z, param_head, p)
        row = {"iteration": k, "beta": beta, "env_steps": steps, "teacher_labels": teacher.labels,
               "samples": len(x), "seconds": round(time.monotonic() - start, 1),
               "reward_per_step": rollouts["reward_per_step"],
               "student_reward_per_step": rollouts["student_reward_per_step"], **stats}
        curve.append(row)
        snapshots.append(policy.record())
        log(f"adaptive: iteration {k}  beta {beta:.3f}  steps {steps}  labels {teacher.labels}  "
            f"{row['seconds']:.0f} s  loss {stats['loss']:.4f}  agreement "
            f"{stats['action_agreement']:.3f}  reward/step {rollouts['reward_per_step']:.3f}"
            + (f"  stuck BCE {stats['stuck_bce']:.4f}" if "stuck_bce" in stats else "")
            + (f"  parameters error {stats['params_mse']:.4f}" if "params_mse" in stats else "")
            + (f"  perturbed {rollouts['perturbed']:.3f}" if rollouts["perturbed"] is not None
               else ""))
    return {"policy": policy.record(), "snapshots": snapshots, "curve": curve,
            "config": config.to_json(), "distribution": dist.text}


class _MemberLog:
    """A member's log in a process of its own: its lines, named, on stdout."""

    def __init__(self, member: int) -> None:
        self.member = member

    def __call__(self, line: str) -> None:
        print(line.replace("adaptive: ", f"adaptive: member {self.member + 1}: ", 1), flush=True)


def _member(dist: TrainingDistribution, config: TrainingConfig, m: int,
            log: Callable[[str], None]) -> dict[str, Any]:
    """Member ``m``: the student of seed ``config.seed + m``, trained alone."""
    return train(dist, dataclasses.replace(config, members=1, seed=config.seed + m), log)


def _train_members(dist: TrainingDistribution, config: TrainingConfig,
                   log: Callable[[str], None], jobs: int = 1) -> dict[str, Any]:
    """``config.members`` students (seeds seed, seed + 1, ...), flown as their
    :func:`ensemble`: one after another, or ``jobs`` at a time in processes of
    their own (spawned, one torch thread each: a member's weights do not depend
    on where it trained). The curve runs through the members' iterations in
    order, steps, labels and seconds adding up (seconds: the members' own,
    summed, the work of one core); its snapshot at a member's iteration k is
    the ensemble of the members before it and that member's student after
    iteration k."""
    if jobs > 1:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        log(f"adaptive: {config.members} members, {min(jobs, config.members)} at a time "
            f"(seeds {config.seed} to {config.seed + config.members - 1})")
        # The workers die with this process, whatever kills it (SIGTERM,
        # SIGKILL): a member left training alone would hold a core for its life.
        with ProcessPoolExecutor(min(jobs, config.members),
                                 mp_context=multiprocessing.get_context("spawn"),
                                 initializer=tie_to, initargs=(os.getpid(),)) as pool:
            futures = [pool.submit(_member, dist, config, m, _MemberLog(m))
                       for m in range(config.members)]
            try:
                parts = [f.result() for f in futures]
            except BaseException:  # a member failed, or Ctrl-C: train no other member
                workers = list(getattr(pool, "_processes", {}).values())
                pool.shutdown(wait=False, cancel_futures=True)
                for worker in workers:
                    worker.terminate()
                raise
    else:
        parts = []
        for m in range(config.members):
            log(f"adaptive: member {m + 1} of {config.members} (seed {config.seed + m})")
            parts.append(_member(dist, config, m, log))
    done: list[HistoryPolicy] = []
    curve, snapshots = [], []
    steps = labels = 0
    seconds = 0.0
    for m, part in enumerate(parts):
        for row, snap in zip(part["curve"], part["snapshots"]):
            curve.append({**row, "member": m, "env_steps": steps + row["env_steps"],
                          "teacher_labels": labels + row["teacher_labels"],
                          "seconds": round(seconds + row["seconds"], 1)})
            snapshots.append(ensemble([*done, HistoryPolicy.from_record(snap)]).record())
        last = part["curve"][-1]
        steps, labels = steps + last["env_steps"], labels + last["teacher_labels"]
        seconds += last["seconds"]
        done.append(HistoryPolicy.from_record(part["policy"]))
    return {"policy": ensemble(done).record(), "snapshots": snapshots, "curve": curve,
            "config": config.to_json(), "distribution": dist.text}
