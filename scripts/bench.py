#!/usr/bin/env python3
"""Every speed figure of the project in one run (a script, not a timed test).

Prints one line per figure, ``name value unit aim ok|MISSED`` (``info`` where
there is no aim), or the same as JSON with ``--json``. The machine is shared
and noisy, so comparisons are ratios of rates measured side by side in
alternating rounds of this one run, and each figure is the median of its
rounds. Figures (the Speed issue's targets; docs/benchmarks.md quotes them):

  cvode_step_changing_us    in-process CVODE step of 1 s with valves changing every
                            step (build/bench_core), aim <= 15 us
  cvode_step_held_us        the same with valves held (CVODE continues)
  lockstep_plant_over_echo  lockstep steps/s from Python over LCM against the real
                            plant / against an echo responder (same messages, no
                            physics), aim >= 0.8
  online_policy_over_echo   the same with the PPO policy choosing every valve, over
                            the echo floor, with the default --ppo-engine, aim >= 0.5
                            (online_torch_/online_native_policy_over_echo: each engine)
  offline_model_steps_per_s offline PPO on the world model (16 rollouts, updates
                            included, as the offline phase runs it) with the native
                            engine (C++ PPO epochs and acting, NumPy model steps),
                            aim >= 50,000
  offline_native_over_torch that rate over the same with the torch engine
  act_native_us / act_numpy_over_native / act_torch_over_native   one act (one state:
                            forward, sampling, log-prob) in C++, in the NumPy oracle
                            (tests/python/oracles) and in torch
  model_env_step_numpy_us / model_env_torch_over_numpy   one step of 16 model envs
  refit_s / refit_numpy_over_torch   a warm world-model refit on one interval
  ppo_run_core_s / ppo_run_lcm_s     one 10-interval PPO online + offline run with
                            pretraining cached, in-process / over LCM, aims 10 / 15 s
                            with the default --ppo-engine (and ppo_run_*_native_ppo_s,
                            ppo_run_*_torch_ppo_s: each engine)
  blas_two_over_one_thread  a policy forward + backward pass on 128 states (distillation's
                            step) with two OpenBLAS threads over one (ftc pins one)
  step_each_over_run        the identifier's one-step predictions of 512 rows, one
                            _core.run call per row over one step_each call
  plan_closed_form_ms       one decision of ppo-robust's planner (64 hold candidates x 10
                            steps, degraded random-08 physics) with the conduit's steps
                            in closed form (linear_step.cpp), as its teacher plans
  plan_cvode_over_closed_form  the same decision with CVODE over the closed form
  distill_step_us           one Adam step of ppo-robust's behaviour cloning (128 rows) in
                            C++ (ftc._learn, the native engine's)
  distill_numpy_over_native the same step in the NumPy oracle over the C++ one
  robust_run_3_intervals_s  ppo-robust (its benchmark arguments), 3 intervals, cached
                            pretraining, in process
  ppo_build_s               building a (native-engine) PPO in a fresh process: its torch
                            optimiser no longer imports torch._dynamo (torch_startup.py)
  ppo_build_with_dynamo_s   the same with torch._dynamo imported first, as torch.optim
                            did before: the difference is what every PPO process paid
  model_mpc_decision_ms     one decision of the model MPC (64 candidates x 10 steps
                            through the world model in NumPy)
  short_run_fresh_python_s / short_run_forked_s   a closed-valves run of 1 x 128 steps
                            as a fresh python, and forked from the experiments' fork
                            server (experiments/fork_server.py): start-up and exit
  realtime_node_hz / realtime_ppo_hz / realtime_mpc_hz   the highest plant rate (of
                            those tried) at which each controller misses fewer than 0.1%
                            of its deadlines on the plant in real-time mode: build/policy_node
                            (2,000 steps per rate), ftc.controller ppo-offline learning on and
                            ftc.mpc oracle-mpc (scripts/bench_realtime.py, which also writes
                            the whole table); aims 100 / 20 / 20 Hz
  vector_steps_per_s        the batched plant pool (FuelTransferVectorEnv, closed form), env
                            steps/s with random valves, the best of N >= 1024 envs at 1 or 2
                            threads (vector_steps_per_s_nN_tT: every N from 1 to 4096),
                            blocks of 128 steps from fresh plants, aim >= 1,000,000
                            (scripts/bench_vector.py; vector_cpu_share: the CPU seconds
                            its process got per wall second, 2 = both cores)
  vector_over_core_env      that rate over gym.make("ftc/FuelTransferCore-v0")'s, stepped
                            the same way in the same rounds, aim >= 50 (vector_steps_per_cpu_s:
                            the pool's steps per CPU-second, 1024 envs, 1 thread: an unshared
                            core's rate; vector_over_core_env_per_cpu_s: over the Core env's)
  sb3_pool_over_subproc_rollouts  SB3 PPO's collect_rollouts through PoolVecEnv over
                            SubprocVecEnv of Core envs, 16 envs each, aim >= 20
                            (sb3_pool_learn_steps_per_s: PPO.learn, updates included;
                            _n8, _n64: the ratio with 8 and 64 envs each; _per_cpu_s: per
                            CPU-second of every process each uses, the workers' included)
  vector_closed_form_level_error_m / _reward_error   the largest difference of the
                            pool's closed-form envs from its CVODE envs over the suite
                            (vector_load_average_before/_after: the 1-minute load average
                            around the scaling table, the machine's share of its 2 cores)
  experiments_full_min, benchmark_suite_min  (--long only) the paper's protocol and
                            the default benchmark suite at --jobs 2, aims 10 / 45 min

Usage: .venv/bin/python scripts/bench.py [--rounds 3] [--json] [--long] [--only NAME...]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np
import torch

from ftc import BUILD_DIR
from ftc.common.build_info import echo_binary
from ftc.experiments.fork_server import ForkServer
from ftc.learning.model_env import ModelEnv
from ftc.learning.offline import pretrained_world_model
from ftc.learning.ppo import PPO, PPOConfig
from ftc.learning.ppo_native import NativeActor, native_distill
from ftc.learning.rollout import train_on_env
from ftc.learning.transitions import Transitions
from ftc.learning.world_model import WorldModel, WorldModelConfig
from ftc.plant import CorePlant, LcmPlant, launch, private_lcm_url, private_prefix

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests" / "python"))  # the NumPy oracle, for comparison
from oracles.ppo_numpy import NumpyActor, numpy_distill  # noqa: E402
SINGLE = str(REPO / "scenarios" / "single.toml")
DEFAULT_ENGINE = PPOConfig().engine  # the controller's --ppo-engine default


@dataclasses.dataclass
class Figure:
    name: str
    value: float
    unit: str
    aim: str = "-"              # e.g. "<= 15"; "-" for information only
    rounds: list[float] = dataclasses.field(default_factory=list)

    @property
    def status(self) -> str:
        if self.aim == "-":
            return "info"
        op, bound = self.aim.split()
        ok = self.value <= float(bound) if op == "<=" else self.value >= float(bound)
        return "ok" if ok else "MISSED"

    def line(self) -> str:
        return f"{self.name:28s} {self.value:12.4g} {self.unit:8s} {self.aim:>10s} {self.status}"


def _median_rounds(rounds: int, *measures: Callable[[], float],
                   rotate: bool = False) -> list[list[float]]:
    """Run the measures in alternating rounds; their values, measure by measure.
    rotate: start each round one measure later than the last (no measure always
    runs right after the same other)."""
    out: list[list[float]] = [[] for _ in measures]
    for k in range(rounds):
        for i in range(len(measures)):
            j = (i + k) % len(measures) if rotate else i
            out[j].append(measures[j]())
    return out


# -- plant ----------------------------------------------------------------------
def bench_cvode(steps: int = 20000) -> list[Figure]:
    out = subprocess.run([str(BUILD_DIR / "bench_core"), str(steps)], capture_output=True,
                         text=True, check=True).stdout
    us = {}
    for line in out.split("\n"):
        if "median_us=" in line:
            name, rest = line.split(None, 1)
            us[name] = float(rest.split("median_us=")[1].split()[0])
    return [Figure("cvode_step_changing_us", us["valves_changing"], "us", "<= 15"),
            Figure("cvode_step_held_us", us["valves_held"], "us")]


def _start_echo() -> LcmPlant:
    url, prefix = private_lcm_url(), private_prefix()
    proc = subprocess.Popen([str(echo_binary()), "--lcm-url", url, "--prefix", prefix])
    return LcmPlant(url, prefix, process=proc)


def _lockstep(link, steps: int, choose: Callable[[np.ndarray], np.ndarray]) -> float:
    o = link.reset()
    start = time.perf_counter()
    for _ in range(steps):
        o = link.step(choose(np.asarray(o.level)))
        if o.done:
            o = link.reset()
    return steps / (time.perf_counter() - start)


def bench_lockstep(rounds: int, steps: int = 250) -> list[Figure]:
    """Lockstep rates over LCM in 8 x ``rounds`` blocks of ``steps`` steps each,
    the order rotated block by block; every figure is the median of its
    per-block ratios to the echo floor. The LCM round trip drifts by several
    times over minutes on this shared machine, and a short block pairs each
    rate with a floor measured within a second of it."""
    rng = np.random.default_rng(0)

    def random_valves(_level: np.ndarray) -> np.ndarray:
        return rng.integers(0, 2, 6)

    def policy(engine: str) -> Callable[[np.ndarray], np.ndarray]:
        ppo = PPO(PPOConfig(engine=engine), seed=0)

        def choose(level: np.ndarray) -> np.ndarray:
            a, _, _ = ppo.act(torch.as_tensor(level, dtype=torch.float32).unsqueeze(0))
            return a[0].numpy().astype(np.int8)
        return choose

    torch_policy, native_policy = policy("torch"), policy("native")
    with launch("scenarios/multiple.toml", 0) as plant, _start_echo() as echo:
        for link in (plant, echo):
            _lockstep(link, 200, random_valves)  # warm up
        echo_r, *rates = _median_rounds(
            8 * rounds, lambda: _lockstep(echo, steps, random_valves),
            lambda: _lockstep(plant, steps, random_valves),
            lambda: _lockstep(plant, steps, torch_policy),
            lambda: _lockstep(plant, steps, native_policy), rotate=True)
    plant_r, torch_r, native_r = ([r / e for r, e in zip(rate, echo_r)] for rate in rates)
    p, q, n = (statistics.median(r) for r in (plant_r, torch_r, native_r))
    default = {"torch": q, "native": n}[DEFAULT_ENGINE]
    return [Figure("lockstep_plant_over_echo", p, "ratio", ">= 0.8", rounds=plant_r),
            Figure("online_policy_over_echo", default, "ratio", ">= 0.5",
                   rounds={"torch": torch_r, "native": native_r}[DEFAULT_ENGINE]),
            Figure("online_torch_policy_over_echo", q, "ratio", rounds=torch_r),
            Figure("online_native_policy_over_echo", n, "ratio", rounds=native_r),
            Figure("lockstep_echo_steps_per_s", statistics.median(echo_r), "steps/s",
                   rounds=echo_r)]


# -- learning ---------------------------------------------------------------------
def _interval_data() -> Transitions:
    """One interval (512 steps) of the degraded plant under random valves."""
    plant = CorePlant(SINGLE, 0, steps_per_interval=512, start_step=512)
    rng = np.random.default_rng(1)
    obs = [plant.reset()]
    for _ in range(512):
        obs.append(plant.step(rng.integers(0, 2, 6)))
        if obs[-1].terminal:
            obs.append(plant.reset())
    return Transitions.from_observations(obs)


def bench_learning(rounds: int) -> list[Figure]:
    torch.set_num_threads(1)
    models = {e: pretrained_world_model(50, 0, "~/.cache/ftc/pretrain", e)
              for e in ("numpy", "torch")}
    data = _interval_data()

    def refit(engine: str) -> Callable[[], float]:
        def run() -> float:
            m = WorldModel(WorldModelConfig(seed=0, engine=engine))
            m.load_state_dict(models[engine][0].state_dict())
            start = time.perf_counter()
            m.fit(data, warm_start=True)
            return time.perf_counter() - start
        return run

    def offline(engine: str) -> Callable[[], float]:
        model, demand, _ = models["numpy"]

        def run() -> float:
            ppo = PPO(PPOConfig(minibatch_size=64, engine=engine), seed=0)
            env = ModelEnv(model, 16, demand, max_episode_steps=512, seed=0,
                           engine="torch" if engine == "torch" else "numpy")
            start = time.perf_counter()
            _, _, steps = train_on_env(ppo, env, 2048, 64)
            return steps / (time.perf_counter() - start)
        return run

    def act(actor: Callable[[torch.Tensor], object], n: int = 3000) -> Callable[[], float]:
        obs = torch.rand(1, 6, generator=torch.Generator().manual_seed(0))

        def run() -> float:
            start = time.perf_counter()
            for _ in range(n):
                actor(obs)
            return 1e6 * (time.perf_counter() - start) / n
        return run

    policy, generator = PPO(PPOConfig(), seed=0).policy, torch.Generator().manual_seed(0)
    native, numpy_actor = NativeActor(policy), NumpyActor(policy)

    def model_step(engine: str, n: int = 500) -> Callable[[], float]:
        model, demand, _ = models["numpy"]
        actions = torch.bernoulli(torch.full((16, 6), 0.3), generator=torch.Generator())

        def run() -> float:
            env = ModelEnv(model, 16, demand, seed=0, engine=engine)
            env.reset()
            start = time.perf_counter()
            for _ in range(n):
                env.step(actions)
            return 1e6 * (time.perf_counter() - start) / n
        return run

    rn, rt, on, ot, an, aa, at, mn, mt = _median_rounds(
        rounds, refit("numpy"), refit("torch"), offline("native"), offline("torch"),
        act(lambda o: native.act(o, generator, False)),
        act(lambda o: numpy_actor.act(o, generator, False)),
        act(lambda o: policy.act(o, generator, False)), model_step("numpy"), model_step("torch"))
    med = statistics.median
    return [Figure("offline_model_steps_per_s", med(on), "steps/s", ">= 50000", on),
            Figure("offline_native_over_torch", med(on) / med(ot), "ratio"),
            Figure("refit_s", med(rn), "s", rounds=rn),
            Figure("refit_numpy_over_torch", med(rt) / med(rn), "ratio"),
            Figure("act_native_us", med(an), "us", rounds=an),
            Figure("act_numpy_over_native", med(aa) / med(an), "ratio"),
            Figure("act_torch_over_native", med(at) / med(an), "ratio"),
            Figure("model_env_step_numpy_us", med(mn), "us", rounds=mn),
            Figure("model_env_torch_over_numpy", med(mt) / med(mn), "ratio")]


# -- ppo-robust's pieces ---------------------------------------------------------------
BLAS_PASS = """
import sys, time, numpy as np
sys.path.insert(0, "tests/python")
from ftc.learning.ppo import ActorCritic
from oracles.ppo_numpy import Net
net, x = Net(ActorCritic()), np.random.default_rng(0).random((128, 6)).astype(np.float32)
start = time.perf_counter()
for _ in range(300):
    logits, value, cache = net.forward(x)
    net.backward(cache, logits, value)
print((time.perf_counter() - start) / 300)
"""


def _blas_pass(threads: int) -> float:
    env = {**os.environ, "OPENBLAS_NUM_THREADS": str(threads)}
    out = subprocess.run([sys.executable, "-c", BLAS_PASS], check=True, cwd=REPO, env=env,
                         capture_output=True, text=True).stdout
    return float(out.split()[-1])


def _distill_step(fit: Callable, epochs: int = 10) -> float:
    """Seconds per Adam step of a behaviour-cloning fit (3,072 rows: 24 minibatches
    of 128 per epoch, as a fit of ppo-robust's 2,048 levels and 1,024 of memory)."""
    import torch

    from ftc.learning.ppo import ActorCritic

    g = torch.Generator().manual_seed(0)
    states = torch.rand(3072, 6, generator=g)
    labels = (torch.rand(3072, 6, generator=g) < 0.5).float()
    torch.manual_seed(0)
    policy = ActorCritic()
    start = time.perf_counter()
    fit(policy, states, labels, epochs=epochs, minibatch=128, lr=1e-3, max_grad_norm=0.5,
        generator=torch.Generator().manual_seed(0))
    return (time.perf_counter() - start) / (epochs * 24)


def _plans(closed_form: bool, count: int = 200) -> float:
    """Seconds per plan of the teacher's planner at ``count`` random levels."""
    from ftc import _core
    from ftc.control.planning.physics.evaluators import ParamsEvaluator
    from ftc.control.planning.planners import HoldPlanner
    from ftc.experiments.suite import write_suite

    with tempfile.TemporaryDirectory() as tmp:
        path = next(p for p in write_suite(Path(tmp)) if p.stem == "random-08")
        scenario = _core.load_scenario(str(path))
    rng = np.random.default_rng(0)
    levels = rng.uniform(0.0, 1.0, (count, 6)) * (rng.uniform(0.0, 1.0, (count, 6)) > 0.2)
    evaluate = ParamsEvaluator(_core.BatchRollout(rtol=1e-6, atol=1e-8,
                                                  exact_active_conduit=closed_form))
    evaluate.params = _core.degraded_params(scenario, 5.0)
    planner = HoldPlanner(3, 10)
    start = time.perf_counter()
    for x in levels:
        planner.plan(evaluate, x)
    return (time.perf_counter() - start) / count


def bench_robust(rounds: int) -> list[Figure]:
    from ftc import _core
    from ftc.experiments.methods import METHODS

    rng = np.random.default_rng(0)
    x, u = rng.uniform(0.0, 1.0, (512, 6)), rng.integers(0, 2, (512, 6))
    params = {"pump": np.full(6, 0.07), "resistance": np.full(6, 130.0)}
    rollout = _core.BatchRollout(rtol=1e-6, atol=1e-8)

    def per_row() -> float:
        start = time.perf_counter()
        for t in range(len(x)):
            rollout.run(x[t], u[t].reshape(1, 1, 6), params, details=True)
        return time.perf_counter() - start

    def each() -> float:
        start = time.perf_counter()
        rollout.step_each(x, u, params)
        return time.perf_counter() - start

    two, one, rows, batch = _median_rounds(rounds, lambda: _blas_pass(2), lambda: _blas_pass(1),
                                           per_row, each)
    native, numpy_steps = _median_rounds(rounds, lambda: _distill_step(native_distill),
                                         lambda: _distill_step(numpy_distill))
    closed, cvode = _median_rounds(rounds, lambda: _plans(True), lambda: _plans(False))
    robust = ["-m", "ftc.controller", *METHODS["ppo-robust"].args, "--scenario", SINGLE,
              "--seed", "0", "--intervals", "3", "--link", "core", "--quiet"]
    _run(robust)  # fills the pretraining cache if it is cold
    run = [_run(robust) for _ in range(rounds)]
    med = statistics.median
    return [Figure("blas_two_over_one_thread", med(two) / med(one), "ratio"),
            Figure("step_each_over_run", med(rows) / med(batch), "ratio"),
            Figure("plan_closed_form_ms", med(closed) * 1e3, "ms",
                   rounds=[r * 1e3 for r in closed]),
            Figure("plan_cvode_over_closed_form", med(cvode) / med(closed), "ratio"),
            Figure("distill_step_us", med(native) * 1e6, "us", rounds=[r * 1e6 for r in native]),
            Figure("distill_numpy_over_native", med(numpy_steps) / med(native), "ratio"),
            Figure("robust_run_3_intervals_s", med(run), "s", rounds=run)]


# -- start-up and the model MPC's decisions -----------------------------------------------
PPO_BUILD = """
import sys, time
import torch
from ftc.learning.ppo import PPO, PPOConfig
start = time.perf_counter()
if sys.argv[1] == "dynamo":
    import torch._dynamo  # what torch.optim's first use imported before torch_startup.py
PPO(PPOConfig(engine="native"), seed=0)
print(time.perf_counter() - start)
"""

MODEL_DECISION = """
import time, numpy as np
from ftc.control.planning.planners import HoldPlanner, ModelEvaluator
from ftc.learning.offline import pretrained_world_model
model, demand, _ = pretrained_world_model(50, 0, "~/.cache/ftc/pretrain", "numpy")
planner, x = HoldPlanner(3, 10), np.array([0.9, 0.8, 0.7, 0.7, 0.8, 0.9])
start = time.perf_counter()
for _ in range(200):
    planner.plan(ModelEvaluator(model, demand), x)
print((time.perf_counter() - start) / 200)
"""


def _python(code: str, *args: str) -> float:
    out = subprocess.run([sys.executable, "-c", code, *args], check=True, cwd=REPO,
                         capture_output=True, text=True).stdout
    return float(out.split()[-1])


def bench_startup(rounds: int) -> list[Figure]:
    _python(MODEL_DECISION)  # fills the pretraining cache if it is cold
    server = ForkServer(["ftc.controller"])
    # a short closed-valves run (1 x 128 steps): start-up and exit are most of it
    args = ["--method", "closed", "--scenario", SINGLE, "--intervals", "1",
            "--steps-per-interval", "128", "--link", "core", "--quiet"]

    def forked() -> float:
        out = Path(tempfile.mkdtemp(prefix="ftc-bench-"))
        (out / "log").write_bytes(b"")
        start = time.perf_counter()
        if server.spawn("ftc.controller", [*args, "--out", str(out / "run")], out / "log").wait():
            raise RuntimeError(f"the forked run failed: {(out / 'log').read_text()[-2000:]}")
        return time.perf_counter() - start

    try:
        marked, imported, decision, fresh, fork = _median_rounds(
            rounds, lambda: _python(PPO_BUILD, "marked"), lambda: _python(PPO_BUILD, "dynamo"),
            lambda: _python(MODEL_DECISION), lambda: _run(["-m", "ftc.controller", *args]),
            forked)
    finally:
        server.close()
    med = statistics.median
    return [Figure("ppo_build_s", med(marked), "s", rounds=marked),
            Figure("ppo_build_with_dynamo_s", med(imported), "s", rounds=imported),
            Figure("model_mpc_decision_ms", 1e3 * med(decision), "ms", rounds=decision),
            Figure("short_run_fresh_python_s", med(fresh), "s", rounds=fresh),
            Figure("short_run_forked_s", med(fork), "s", rounds=fork),
            Figure("short_run_fresh_over_forked", med(fresh) / med(fork), "ratio")]


# -- whole runs ---------------------------------------------------------------------
def _run(args: list[str]) -> float:
    out = tempfile.mkdtemp(prefix="ftc-bench-")
    start = time.perf_counter()
    subprocess.run([sys.executable, *args, "--out", out], check=True, cwd=REPO,
                   stdout=subprocess.DEVNULL)
    return time.perf_counter() - start


def bench_runs(rounds: int) -> list[Figure]:
    base = ["-m", "ftc.controller", "--method", "ppo", "--pretrain", "--scenario", SINGLE,
            "--seed", "0", "--quiet"]
    _run([*base, "--link", "core"])  # fills the pretraining cache if it is cold
    runs = {(link, engine): lambda link=link, engine=engine: _run(
                [*base, "--link", link, "--ppo-engine", engine])
            for engine in ("native", "torch") for link in ("core", "lcm")}
    times = dict(zip(runs, _median_rounds(rounds, *runs.values())))
    med = statistics.median
    aims = {"core": "<= 10", "lcm": "<= 15"}
    return ([Figure(f"ppo_run_{link}_s", med(times[link, DEFAULT_ENGINE]), "s", aims[link],
                    times[link, DEFAULT_ENGINE]) for link in ("core", "lcm")]
            + [Figure(f"ppo_run_{link}_{engine}_ppo_s", med(times[link, engine]), "s",
                      rounds=times[link, engine])
               for engine in ("native", "torch") for link in ("core", "lcm")])


def bench_realtime(rounds: int) -> list[Figure]:
    import bench_realtime as rt

    rows, _ = rt.measure(["node", "ppo", "mpc"], 2000, [100, 200, 500, 1000], [20, 50, 100])
    aims = {"node": ">= 100", "ppo": ">= 20", "mpc": ">= 20"}
    return [Figure(f"realtime_{c}_hz", rt.highest_rate(rows, c) or 0.0, "Hz", aims[c])
            for c in ("node", "ppo", "mpc")]


def bench_vector(rounds: int) -> list[Figure]:
    import bench_vector as bv

    load_before = os.getloadavg()[0]
    rows, core, core_rate = bv.scaling(rounds)
    load_after = os.getloadavg()[0]
    rate = {(int(r["threads"]), int(r["num_envs"])): float(r["steps_per_s"]) for r in rows}
    row = {(int(r["threads"]), int(r["num_envs"])): r for r in rows}
    best_key = max((key for key in rate if key[1] >= 1024), key=rate.get)
    best = rate[best_key]
    one_core = float(row[(1, 1024)]["steps_per_cpu_s"])
    sb3 = {n: bv.sb3_rates(n, rounds) for n in bv.SB3_SIZES}
    level, reward, ends = bv.closed_form_error()
    med = statistics.median
    return ([Figure("vector_steps_per_s", best, "steps/s", ">= 1000000"),
             Figure("vector_over_core_env", best / med(core), "ratio", ">= 50"),
             Figure("core_env_steps_per_s", med(core), "steps/s", rounds=core),
             # CPU seconds the best configuration's process got per wall second (2 = both cores)
             Figure("vector_cpu_share", float(row[best_key]["cpu_share"]), "cpus"),
             Figure("vector_steps_per_cpu_s", one_core, "steps/s"),
             Figure("vector_over_core_env_per_cpu_s", one_core / med(core_rate.cpu_rates),
                    "ratio")]
            + [Figure(f"vector_steps_per_s_n{n}_t{t}", v, "steps/s")
               for (t, n), v in sorted(rate.items())]
            + [Figure("sb3_pool_over_subproc_rollouts", sb3[16]["pool"] / sb3[16]["subproc"],
                      "ratio", ">= 20"),
               Figure("sb3_pool_rollout_steps_per_s", sb3[16]["pool"], "steps/s"),
               Figure("sb3_subproc_rollout_steps_per_s", sb3[16]["subproc"], "steps/s"),
               Figure("sb3_pool_learn_steps_per_s", sb3[16]["learn"], "steps/s"),
               Figure("sb3_pool_over_subproc_rollouts_per_cpu_s",
                      sb3[16]["pool_cpu"] / sb3[16]["subproc_cpu"], "ratio")]
            + [Figure(f"sb3_pool_over_subproc_rollouts_n{n}{per}",
                      r["pool" + cpu] / r["subproc" + cpu], "ratio")
               for n, r in sorted(sb3.items()) if n != 16
               for per, cpu in (("", ""), ("_per_cpu_s", "_cpu"))]
            + [Figure("vector_closed_form_level_error_m", level, "m"),
               Figure("vector_closed_form_reward_error", reward, "reward"),
               Figure("vector_closed_form_episode_ends_differing", ends, "steps"),
               # the machine's 1-minute load average around the scaling table (2 cores)
               Figure("vector_load_average_before", load_before, "runnable"),
               Figure("vector_load_average_after", load_after, "runnable")])


def bench_long() -> list[Figure]:
    full = _run(["-m", "ftc.experiments", "all", "--full", "--jobs", "2"]) / 60
    suite = _run(["-m", "ftc.experiments", "benchmark", "--jobs", "2"]) / 60
    return [Figure("experiments_full_min", full, "min", "<= 10"),
            Figure("benchmark_suite_min", suite, "min", "<= 45")]


GROUPS: dict[str, Callable[[int], list[Figure]]] = {
    "cvode": lambda rounds: bench_cvode(), "lockstep": bench_lockstep,
    "learning": bench_learning, "robust": bench_robust, "startup": bench_startup,
    "runs": bench_runs, "realtime": bench_realtime, "vector": bench_vector}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds per figure")
    parser.add_argument("--json", action="store_true", help="print the figures as JSON")
    parser.add_argument("--results", type=Path, metavar="CSV",
                        help="also write the figures to this result file (e.g. "
                             "docs/results/bench.csv, rendered in docs/benchmarks.md)")
    parser.add_argument("--long", action="store_true",
                        help="also time the paper's protocol and the benchmark suite (an hour)")
    parser.add_argument("--only", nargs="+", choices=sorted(GROUPS), metavar="GROUP",
                        help=f"run only these groups ({', '.join(sorted(GROUPS))})")
    args = parser.parse_args()
    if args.rounds < 1:
        parser.error("--rounds must be >= 1")
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    figures: list[Figure] = []
    for name, group in GROUPS.items():
        if args.only and name not in args.only:
            continue
        new = group(args.rounds)
        figures += new
        if not args.json:
            for f in new:
                print(f.line(), flush=True)
    if args.long:
        new = bench_long()
        figures += new
        if not args.json:
            for f in new:
                print(f.line(), flush=True)
    if args.json:
        print(json.dumps([{**dataclasses.asdict(f), "status": f.status} for f in figures],
                         indent=2))
    if args.results:
        _write_results(args.results, figures, args)
    return 0


def _write_results(path: Path, figures: list[Figure], args: argparse.Namespace) -> None:
    """The figures as a result file: provenance lines, then figure, value, unit, aim, status."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from suite_results import write_result_file  # the one writer of result files

    from ftc.common.build_info import git_revision

    flags = [f"--rounds {args.rounds}", *(["--long"] if args.long else []),
             *([f"--only {' '.join(args.only)}"] if args.only else [])]
    provenance = (f"# what: speed figures, the median of {args.rounds} alternating rounds "
                  "each (scripts/bench.py)\n"
                  f"# command: scripts/bench.py {' '.join(flags)}\n"
                  f"# commit: {git_revision()}\n# date: {time.strftime('%Y-%m-%d')}\n")
    write_result_file(path, provenance, [
        {"figure": f"`{f.name}`", "value": f"{f.value:.4g}", "unit": f.unit, "aim": f.aim,
         "status": f.status} for f in figures])


if __name__ == "__main__":
    sys.exit(main())
