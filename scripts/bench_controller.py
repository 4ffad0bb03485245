#!/usr/bin/env python3
"""Controller benchmark (issue 3's Benchmark section; a script, not a timed test:
the machine is shared and noisy, so the LCM figures are measured in alternating
rounds and the median is printed).

Prints:
  * real steps/s of the online loop over LCM against the real plant process with
    the policy in the loop, without PPO updates and with them (t_update = 128),
    against the echo floor (build/lcm_echo: the same messages, no physics, no
    policy); aim: online >= half the echo floor;
  * offline model steps/s: the world model env (16 rollouts side by side) with
    the policy acting, without and with PPO updates; aim: >= 50,000;
  * seconds per world-model refit (warm start on one interval of real data);
  * the wall time of one full 10-interval run with offline learning (sequential),
    through the command line with its own plant: without pretraining, and with
    --pretrain from the cache (pretrained first if not cached); aim: < 60 s.

Usage: .venv/bin/python scripts/bench_controller.py [--steps 2048] [--rounds 3] [--no-full]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from ftc.common.build_info import echo_binary
from ftc.control.controller_cli import Controller
from ftc.control.ppo_agent import ControllerConfig
from ftc.learning.rollout import train_on_env
from ftc.plant import LcmPlant, LinkConfig, launch, private_lcm_url, private_prefix
from ftc.learning.ppo import PPO, PPOConfig

REPO = Path(__file__).resolve().parents[1]
SCENARIO = str(REPO / "scenarios" / "single.toml")


def start_echo() -> LcmPlant:
    url, prefix = private_lcm_url(), private_prefix()
    proc = subprocess.Popen([str(echo_binary()), "--lcm-url", url, "--prefix", prefix])
    return LcmPlant(url, prefix, process=proc)


def echo_rate(link: LcmPlant, steps: int, rng: np.random.Generator) -> float:
    """Lockstep round trips per second with no physics and no policy (the floor)."""
    link.reset()
    valves = rng.integers(0, 2, (steps, 6))
    start = time.perf_counter()
    for u in valves:
        if link.step(u).done:
            link.reset()
    return steps / (time.perf_counter() - start)


def policy_rate(ctrl: Controller, plant: LcmPlant, steps: int) -> float:
    """The online loop's stepping with the policy choosing every valve, no updates."""
    o = plant.reset()
    start = time.perf_counter()
    for _ in range(steps):
        u, _ = ctrl._valves(o.level)
        o = plant.step(u)
        if o.done:
            o = plant.reset()
    rate = steps / (time.perf_counter() - start)
    while not o.truncated:  # on to the interval boundary (Controller.online starts there)
        o = plant.step(np.zeros(6, np.int8))
        if o.terminal and not o.truncated:
            o = plant.reset()
    return rate


def update_rate(ctrl: Controller, plant: LcmPlant) -> float:
    """One online interval of Controller.online: policy, caching and a PPO update
    every t_update steps (the plant's interval length must match)."""
    start = time.perf_counter()
    ctrl.online(plant)
    ctrl.interval += 1
    return ctrl.cfg.steps_per_interval / (time.perf_counter() - start)


def bench_online(steps: int, rounds: int) -> tuple[dict, list]:
    cfg = ControllerConfig(out=tempfile.mkdtemp(prefix="ftc-bench-"), offline=False,
                           quiet=True, scenario=SCENARIO)
    ctrl = Controller(cfg, PPOConfig())
    rng = np.random.default_rng(0)
    rates: dict[str, list[float]] = {"echo": [], "policy": [], "policy+updates": []}
    cfg_link = LinkConfig(retry_timeout=0.05, backoff=2.0)
    with launch(SCENARIO, 0, extra_args=["--steps-per-interval", str(cfg.steps_per_interval)],
                config=cfg_link) as plant, start_echo() as echo:
        echo_rate(echo, 200, rng), policy_rate(ctrl, plant, 200)  # warm up
        for _ in range(rounds):
            rates["echo"].append(echo_rate(echo, steps, rng))
            rates["policy"].append(policy_rate(ctrl, plant, steps))
            for _ in range(max(1, steps // cfg.steps_per_interval)):
                rates["policy+updates"].append(update_rate(ctrl, plant))
    return {k: statistics.median(v) for k, v in rates.items()}, rates


def bench_offline() -> dict[str, float]:
    """Model env steps/s with the policy acting (no updates, and PPO as the offline
    phase runs it), and seconds per warm-started refit on one interval of data."""
    from ftc.learning.model_env import ModelEnv, estimate_demand
    from ftc.learning.transitions import Transitions, collect_nominal_dataset
    from ftc.learning.world_model import WorldModel, WorldModelConfig
    from ftc.plant import CorePlant

    torch.set_num_threads(1)
    data = collect_nominal_dataset(50, seed=0)
    model = WorldModel(WorldModelConfig(seed=0))
    start = time.perf_counter()
    model.fit(data, warm_start=False)
    pretrain_fit = time.perf_counter() - start
    demand = estimate_demand(data)

    # one interval (512 steps) of real data from the degraded plant, random valves
    plant = CorePlant(SCENARIO, 0, steps_per_interval=512, start_step=512)
    rng = np.random.default_rng(1)
    obs = [plant.reset()]
    for _ in range(512):
        o = plant.step(rng.integers(0, 2, 6))
        obs.append(o)
        if o.terminal:
            obs.append(plant.reset())
    interval = Transitions.from_observations(obs)
    refits = []
    for _ in range(3):
        m = WorldModel(WorldModelConfig(seed=0))
        m.load_state_dict(model.state_dict())
        start = time.perf_counter()
        m.fit(interval, warm_start=True)
        refits.append(time.perf_counter() - start)

    ppo = PPO(PPOConfig(minibatch_size=64), seed=0)
    env = ModelEnv(model, 16, demand, max_episode_steps=512, seed=0)
    x = env.reset()
    n = 4096 // 16
    start = time.perf_counter()
    for _ in range(n):
        a, _, _ = ppo.act(x)
        x = env.step(a).obs
    act_rate = n * 16 / (time.perf_counter() - start)
    start = time.perf_counter()
    _, _, steps = train_on_env(ppo, env, 4096, 64)
    train_rate = steps / (time.perf_counter() - start)
    return {"model_steps_per_s_policy": act_rate, "model_steps_per_s_with_updates": train_rate,
            "refit_s": statistics.median(refits), "nominal_fit_s": pretrain_fit}


def full_run(extra: list[str]) -> dict[str, float]:
    out = tempfile.mkdtemp(prefix="ftc-bench-run-")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(REPO / "python"), str(REPO / "build" / "lcmtypes"), str(REPO / "build" / "python"),
         os.environ.get("PYTHONPATH", "")])}
    start = time.perf_counter()
    subprocess.run([sys.executable, "-m", "ftc.controller", "--scenario", SCENARIO, "--seed", "0",
                    "--quiet", "--out", out, *extra], check=True, env=env, cwd=REPO)
    wall = time.perf_counter() - start
    info = torch.load(Path(out) / "checkpoint.pt", weights_only=True)["info"]
    done = json.loads((Path(out) / "done.json").read_text())
    return {"wall_s": wall, "intervals_s": done["wall_time"],
            "pretrain_cached": info.get("pretrain_cached", -1)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--steps", type=int, default=2048, help="lockstep steps per round")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds")
    parser.add_argument("--no-full", dest="full", action="store_false",
                        help="skip the two full 10-interval runs")
    args = parser.parse_args()
    torch.set_num_threads(1)

    med, rates = bench_online(args.steps, args.rounds)
    print(f"online loop over LCM (median of {args.rounds} alternating rounds of {args.steps}):")
    for key, label in (("echo", "echo floor (no physics, no policy)"),
                       ("policy", "plant + policy, no updates"),
                       ("policy+updates", "plant + policy + PPO update every 128")):
        r = ", ".join(f"{x:.0f}" for x in rates[key])
        print(f"  {label:40s} {med[key]:7.0f} steps/s  ({r})")
    print(f"  ratio policy/echo = {med['policy'] / med['echo']:.2f}, "
          f"with updates/echo = {med['policy+updates'] / med['echo']:.2f}  (aim >= 0.5)")

    off = bench_offline()
    print("offline (world model, 16 rollouts side by side):")
    print(f"  model steps/s, policy acting         {off['model_steps_per_s_policy']:9.0f}")
    print(f"  model steps/s, with PPO updates      {off['model_steps_per_s_with_updates']:9.0f}"
          "  (aim >= 50,000)")
    print(f"  world-model refit (warm, 512 steps)  {off['refit_s']:9.2f} s "
          f"(nominal pretraining fit {off['nominal_fit_s']:.2f} s)")

    if args.full:
        print("full 10-interval run, offline learning (sequential), own plant over LCM:")
        for label, extra in (("no pretraining", []), ("--pretrain (cached)", ["--pretrain"])):
            r = full_run(extra)
            cached = {1: "cache hit", 0: "pretrained now", -1: ""}[int(r["pretrain_cached"])]
            print(f"  {label:22s} {r['wall_s']:6.1f} s wall ({r['intervals_s']:.1f} s in the "
                  f"intervals) {cached}  (aim < 60 s)")


if __name__ == "__main__":
    main()
