"""Train Stable-Baselines3 PPO on the batched plant pool over a distribution of
faults, logging steps/s and returns to TensorBoard.

    OMP_NUM_THREADS=1 python examples/train_vector.py --minutes 10 --envs 256 \\
        --tensorboard runs/train_vector/tb --out runs/train_vector/model.zip

The pool (ftc.plant.vector, in SB3's same-step autoreset through
ftc.plant.sb3_vec.PoolVecEnv) holds --envs plants, each with a scenario drawn
from the distribution below and renewed (a fresh plant, a fresh draw) after
--life intervals of 512 steps, so the policy sees young and worn plants with
faults on either wing. Training stops at --steps or after --minutes of wall
time, whichever comes first. Then the policy (deterministic: valve open iff
p > 0.5) and all valves closed (the optimal policy of a healthy plant) are
evaluated side by side on the same held-out draw of plants (--eval-envs
plants, each run for its whole life).

TensorBoard (--tensorboard DIR): SB3's own scalars (time/fps, the losses,
rollout/ep_rew_mean of VecMonitor's episode returns) and this script's
``pool/steps_per_s`` and ``pool/reward_per_step`` (the plant's reward, before
VecNormalize's scaling) per rollout. One line per rollout on stdout as well.

Exit codes: 0 done, 2 bad input (one line: ``train_vector: error: ...``),
5 the model could not be saved.
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.vec_env import VecMonitor, VecNormalize

from ftc.common.errors import EXIT_STORAGE, EXIT_USAGE
from ftc.plant.sb3_vec import PoolVecEnv
from ftc.plant.vector import FuelTransferVectorEnv

# Faults on either wing: each tank worn with probability 0.25, each engine with
# 0.5, factors in the suite's [6, 30]; one plant in five loses a pump within its
# life, one in five a valve sticks, one in four has sensor noise.
DISTRIBUTION = dict(tank_probability=0.25, tank_factor=[6.0, 30.0], engine_probability=0.5,
                    engine_factor=[6.0, 30.0], dead_pump_probability=0.2,
                    stuck_valve_probability=0.2, noise_probability=0.25,
                    noise_std=[0.0, 0.005])


@dataclass
class Config:
    """A run. PPO's settings are SB3's defaults except: learning rate 1e-3 and
    gamma 0.9 (examples/sb3_ppo.py says why), rewards scaled by VecNormalize."""

    minutes: float = 10.0
    steps: int = 10**9
    envs: int = 256
    n_steps: int = 64          # per env per rollout: a rollout is envs * n_steps steps
    batch_size: int = 4096
    n_epochs: int = 4
    life: int = 10             # intervals before a plant is renewed
    seed: int = 0
    eval_envs: int = 64
    tensorboard: str | None = None
    out: str | None = None
    results: str | None = None  # the curve as a result file (docs/results/), if given


class PoolLog(BaseCallback):
    """Per rollout: steps/s so far and the plant's mean reward per step."""

    def __init__(self, deadline: float) -> None:
        super().__init__()
        self.deadline, self.start = deadline, time.monotonic()
        self.rewards: list[float] = []
        self.curve: list[tuple[int, float, float]] = []  # (steps, seconds, reward per step)

    def _on_step(self) -> bool:
        self.rewards.append(float(self.model.get_vec_normalize_env().get_original_reward().mean()))
        return time.monotonic() < self.deadline or not self.curve  # one rollout at least

    def _on_rollout_end(self) -> None:
        elapsed = time.monotonic() - self.start
        rate, reward = self.num_timesteps / elapsed, float(np.mean(self.rewards))
        self.rewards = []
        self.curve.append((self.num_timesteps, elapsed, reward))
        self.logger.record("pool/steps_per_s", rate)
        self.logger.record("pool/reward_per_step", reward)
        print(f"steps {self.num_timesteps:10d}  {elapsed:6.0f} s  {rate:8.0f} steps/s  "
              f"reward/step {reward:.3f}", flush=True)


def evaluate(policy, config: Config) -> float:
    """Mean reward per step over eval_envs held-out plants, each for its whole
    life (life x 512 steps); policy(obs) -> (N, 6) valves."""
    env = FuelTransferVectorEnv(config.eval_envs, DISTRIBUTION | {"life_intervals": config.life},
                                plant_seed=10**6 + config.seed, life_intervals=0)
    obs, _ = env.reset()
    total = 0.0
    steps = config.life * 512
    for _ in range(steps):
        obs, reward, *_ = env.step(policy(obs))
        total += float(reward.mean())
    return total / steps


def train(config: Config) -> tuple[PPO, PoolLog, float]:
    torch.set_num_threads(1)
    deadline = time.monotonic() + 60 * config.minutes
    venv = PoolVecEnv(num_envs=config.envs,
                      scenario=DISTRIBUTION | {"life_intervals": config.life},
                      plant_seed=config.seed)
    venv = VecNormalize(VecMonitor(venv), norm_obs=False, norm_reward=True, gamma=0.9)
    model = PPO("MlpPolicy", venv, n_steps=config.n_steps, batch_size=config.batch_size,
                n_epochs=config.n_epochs, learning_rate=1e-3, gamma=0.9, seed=config.seed,
                device="cpu", tensorboard_log=config.tensorboard, verbose=0)
    log = PoolLog(deadline)
    start = time.monotonic()
    model.learn(total_timesteps=config.steps, callback=log, tb_log_name="train_vector")
    return model, log, time.monotonic() - start


def parse_args(argv: list[str] | None = None) -> Config:
    d = Config()
    p = argparse.ArgumentParser(prog="train_vector", description=__doc__.split("\n\n")[0])
    p.add_argument("--minutes", type=float, default=d.minutes, help="wall-time budget")
    p.add_argument("--steps", type=int, default=d.steps, help="env steps budget")
    p.add_argument("--envs", type=int, default=d.envs, help="plants in the pool")
    p.add_argument("--n-steps", type=int, default=d.n_steps, help="steps per env per rollout")
    p.add_argument("--life", type=int, default=d.life, help="intervals of a plant's life")
    p.add_argument("--seed", type=int, default=d.seed)
    p.add_argument("--eval-envs", type=int, default=d.eval_envs)
    p.add_argument("--tensorboard", default=None, help="TensorBoard log directory")
    p.add_argument("--out", default=None, help="save the model here (.zip)")
    p.add_argument("--results", default=None,
                   help="write the curve (steps, seconds, reward per step per rollout) and "
                        "the evaluation as a result file (CSV, e.g. docs/results/train_vector.csv)")
    a = p.parse_args(argv)
    for name in ("minutes", "steps", "envs", "n_steps", "life", "eval_envs"):
        if not getattr(a, name) > 0:
            p.error(f"argument --{name.replace('_', '-')}: must be > 0")
    return Config(minutes=a.minutes, steps=a.steps, envs=a.envs, n_steps=a.n_steps,
                  batch_size=min(d.batch_size, a.envs * a.n_steps), life=a.life, seed=a.seed,
                  eval_envs=a.eval_envs, tensorboard=a.tensorboard, out=a.out,
                  results=a.results)


def main(argv: list[str] | None = None) -> int:
    config = parse_args(argv)
    try:
        model, log, seconds = train(config)
    except ValueError as e:
        print(f"train_vector: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    if config.out:
        try:
            Path(config.out).parent.mkdir(parents=True, exist_ok=True)
            model.save(config.out)
        except OSError as e:
            print(f"train_vector: error: cannot save the model to {config.out}: {e}",
                  file=sys.stderr)
            return EXIT_STORAGE
    learned = evaluate(lambda o: model.predict(o, deterministic=True)[0].astype(np.int8), config)
    closed = evaluate(lambda o: np.zeros((len(o), 6), np.int8), config)
    first, last = log.curve[0][2], log.curve[-1][2]
    print(f"trained {model.num_timesteps} steps in {seconds:.0f} s "
          f"({model.num_timesteps / seconds:.0f} steps/s, updates included); reward/step per "
          f"rollout {first:.3f} -> {last:.3f}")
    print(f"held-out plants ({config.eval_envs} x {config.life} intervals): reward/step "
          f"policy {learned:.3f}, all valves closed {closed:.3f}")
    if config.results:
        write_results(Path(config.results), config, log, seconds, learned, closed)
    return 0


def write_results(path: Path, config: Config, log: PoolLog, seconds: float, learned: float,
                  closed: float) -> None:
    """The curve, every rollout's row, with the run's provenance and evaluation."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    from suite_results import write_result_file  # the one writer of result files

    from ftc.common.build_info import git_revision

    provenance = (f"# what: examples/train_vector.py, SB3 PPO on the plant pool ({config.envs} "
                  f"envs) over its fault distribution: per rollout, env steps so far, wall "
                  f"seconds (updates included) and the plant's mean reward per step; "
                  f"{seconds:.0f} s in all; held-out plants ({config.eval_envs} x "
                  f"{config.life} intervals) reward per step: policy {learned:.3f}, all valves "
                  f"closed {closed:.3f}\n"
                  f"# command: examples/train_vector.py --minutes {config.minutes:g} --envs "
                  f"{config.envs} --seed {config.seed}\n"
                  f"# commit: {git_revision()}\n# date: {time.strftime('%Y-%m-%d')}\n")
    write_result_file(path, provenance, [
        {"steps": steps, "seconds": f"{t:.0f}", "reward_per_step": f"{r:.3f}"}
        for steps, t, r in log.curve])


if __name__ == "__main__":
    sys.exit(main())
