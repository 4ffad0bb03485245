"""The adaptive policy's "no teacher" ablation (docs/adaptive.md): the same
student (a window of levels and valves, tanh MLP, six valve logits) trained
by RL alone, Stable-Baselines3 PPO on the reward, on the same plants DAgger
meets (the training distribution's draws, seed ``seed * 1000 + k`` for the
k-th batch of ``--envs`` plants, each run for its whole life) and the same
budget of environment steps as one DAgger student (the default: 8 x 48 plants x 10 x 512).

    OMP_NUM_THREADS=1 python scripts/adaptive_rl.py --out /tmp/rl.pt
    python -m ftc.experiments.adaptive evaluate --checkpoint /tmp/rl.pt --sets suite check

The checkpoint is the actor's weights in the student's layout
(``ftc.learning.history_policy.HistoryPolicy``: SB3's deterministic action
for a MultiBinary space opens a valve where its logit is positive, as the
student does), so ``evaluate`` scores it exactly as it scores the student.
PPO's settings are examples/train_vector.py's (learning rate 1e-3, gamma 0.9,
rewards scaled by VecNormalize).

With ``--init CHECKPOINT`` it fine-tunes a distilled student instead (one
member, either head; the joint head's 64 logits are PPO's categorical action):
the actor starts as the student, the critic is trained alone for ``--warmup``
steps (the actor frozen, so that the first updates follow a fitted value),
then both, on the true reward; ``--seed`` other than the student's draws
other plants. The fine-tune measured in docs/adaptive.md ("Variants"):

    OMP_NUM_THREADS=1 python scripts/adaptive_rl.py --init MEMBER.pt --seed 100 \
        --steps 1500000 --warmup 600000 --lr 3e-5 --gamma 0.99 --clip 0.1 \
        --target-kl 0.01 --out /tmp/fine-tuned.pt

Exit codes: 0 done, 2 bad input, 5 the checkpoint could not be written.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from stable_baselines3 import PPO
from stable_baselines3.common.vec_env import VecEnv, VecNormalize

from ftc.common.atomic import atomic_torch_save
from ftc.common.errors import EXIT_STORAGE, EXIT_USAGE
from ftc.control.planning.planners import valve_settings
from ftc.experiments.adaptive import distribution
from ftc.learning.history_policy import (HistoryPolicy, HistoryWindow, StudentConfig,
                                         TrainingConfig)
from ftc.plant.vector import FuelTransferVectorEnv

SETTINGS = valve_settings().astype(np.int8)  # (64, 6): setting a opens valve i iff bit i


class DrawnPlants(VecEnv):
    """``envs`` plants of the distribution, their observation the student's
    window; when the batch has lived its life every env is done and the next
    batch of draws replaces it (DAgger's k-th iteration's plants)."""

    def __init__(self, dist: distribution.TrainingDistribution, config: TrainingConfig) -> None:
        self.dist, self.config, self.batch = dist, config, -1
        self.life_steps = config.life_intervals * dist.steps_per_interval
        inputs = StudentConfig(window=config.window).inputs
        self.joint = config.head == "joint"  # a setting's number: valve i open iff bit i
        super().__init__(config.envs, spaces.Box(-1.0, 1.0, (inputs,), np.float32),
                         spaces.Discrete(2 ** 6) if self.joint else spaces.MultiBinary(6))
        self.env: FuelTransferVectorEnv | None = None
        self._actions = np.zeros((config.envs, 6), np.int8)

    def _next_batch(self) -> np.ndarray:
        if self.env is not None:
            self.env.close()
        self.batch += 1
        c = self.config
        scenarios = distribution.draw(self.dist, c.envs,
                                      distribution.draw_seed(c.seed, self.batch))
        self.env = FuelTransferVectorEnv(c.envs, scenarios, plant_seed=c.seed * 10**6 +
                                         self.batch * c.envs, autoreset="same_step", threads=1,
                                         copy=False)
        obs, _ = self.env.reset()
        self.window = HistoryWindow(c.envs, c.window)
        self.window.start(obs)
        self.t = 0
        return self.window.features()

    def reset(self) -> np.ndarray:
        return self._next_batch() if self.env is None else self.window.features()

    def step_async(self, actions: np.ndarray) -> None:
        if self.joint:
            self._actions = SETTINGS[np.asarray(actions, np.int64).reshape(-1)]
        else:
            self._actions = np.asarray(actions, np.int8)

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        obs, reward, terminated, truncated, _ = self.env.step(self._actions)
        dones = terminated | truncated
        self.window.push(obs, self._actions, dones)
        self.t += 1
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        features = self.window.features()
        if self.t >= self.life_steps:
            dones = np.ones(self.num_envs, bool)
            for i in range(self.num_envs):
                infos[i] = {"terminal_observation": features[i], "TimeLimit.truncated": True}
            features = self._next_batch()
        return features, reward.astype(np.float32), dones, infos

    def close(self) -> None:
        if self.env is not None:
            self.env.close()

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        return [getattr(self, attr_name)] * self.num_envs

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *args: Any, indices: Any = None, **kw: Any) -> list:
        return [getattr(self, method_name)(*args, **kw)]

    def env_is_wrapped(self, wrapper_class: Any, indices: Any = None) -> list[bool]:
        return [False] * self.num_envs


def actor_layers(model: PPO) -> list[torch.nn.Linear]:
    actor = model.policy.mlp_extractor.policy_net
    return [m for m in actor if isinstance(m, torch.nn.Linear)] + [model.policy.action_net]


def copy_layers(dst: list[torch.nn.Linear], src: list[torch.nn.Linear]) -> None:
    with torch.no_grad():
        for d, s in zip(dst, src, strict=True):
            d.weight.copy_(s.weight)
            d.bias.copy_(s.bias)


def student_record(model: PPO, config: TrainingConfig) -> dict[str, Any]:
    """The actor as a :class:`HistoryPolicy` record (same layers, same rule)."""
    student = HistoryPolicy(config.student())
    copy_layers([m for m in student.net if isinstance(m, torch.nn.Linear)], actor_layers(model))
    return student.record()


def load_student(path: str) -> HistoryPolicy:
    """The student of a checkpoint of one member (ValueError otherwise)."""
    try:
        record = torch.load(path, weights_only=True)
        student = HistoryPolicy.from_record(record["policy"])
    except (OSError, RuntimeError, KeyError, TypeError, ValueError, EOFError) as e:
        raise ValueError(f"--init {path}: not a student checkpoint ({e})") from None
    if int(record.get("config", {}).get("members", 1)) != 1:
        raise ValueError(f"--init {path}: a checkpoint of {record['config']['members']} "
                         f"members; fine-tune one member (train --members 1)")
    return student


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="the checkpoint (.pt)")
    p.add_argument("--distribution", default=str(distribution.DISTRIBUTION_FILE))
    p.add_argument("--steps", type=int, default=0,
                   help="env steps (default: DAgger's, iterations x envs x life x 512)")
    p.add_argument("--envs", type=int, default=TrainingConfig().envs)
    p.add_argument("--life-intervals", type=int, default=TrainingConfig().life_intervals,
                   help="intervals each batch of plants lives")
    p.add_argument("--n-steps", type=int, default=256, help="steps per env per rollout")
    p.add_argument("--seed", type=int, default=0,
                   help="plants (the training draws of this seed), PPO's sampling and weights")
    p.add_argument("--init", default=None, metavar="CHECKPOINT",
                   help="fine-tune this student (one member) instead of starting from scratch")
    p.add_argument("--warmup", type=int, default=0,
                   help="with --init: steps that train the critic alone first (default 0)")
    p.add_argument("--lr", type=float, default=1e-3, help="Adam's learning rate (default 1e-3)")
    p.add_argument("--gamma", type=float, default=0.9, help="discount (default 0.9)")
    p.add_argument("--clip", type=float, default=0.2, help="PPO's clip range (default 0.2)")
    p.add_argument("--target-kl", type=float, default=None,
                   help="stop an update's epochs where the KL to the rollout's policy passes "
                        "this (default: none)")
    a = p.parse_args(argv)
    try:
        if a.envs < 1 or a.n_steps < 1 or a.steps < 0 or a.life_intervals < 1 or a.warmup < 0:
            raise ValueError("--envs, --n-steps and --life-intervals must be >= 1, --steps and "
                             "--warmup >= 0")
        if not (a.lr > 0 and 0 < a.gamma <= 1 and a.clip > 0):
            raise ValueError("--lr and --clip must be > 0, --gamma in (0, 1]")
        if a.warmup and a.init is None:
            raise ValueError("--warmup goes with --init")
        dist = distribution.load(a.distribution)
        if a.life_intervals > dist.life_intervals:
            raise ValueError(f"--life-intervals {a.life_intervals} exceeds the distribution's "
                             f"{dist.life_intervals}")
        init = load_student(a.init) if a.init else None
        if init is not None and init.config.stuck_memory:
            raise ValueError(f"--init {a.init}: a student with the stuck memory; this script's "
                             "plants feed windows alone")
    except ValueError as e:
        print(f"adaptive_rl: error: {e}", file=sys.stderr)
        return EXIT_USAGE
    shape = ({"head": "valves"} if init is None else
             {"head": init.config.head, "window": init.config.window,
              "hidden": init.config.hidden})
    config = TrainingConfig(envs=a.envs, seed=a.seed, life_intervals=a.life_intervals,
                            regret=0.0, stuck_memory=False, teacher_stuck="all", **shape)
    steps = a.steps or config.iterations * config.envs * config.life_intervals * \
        dist.steps_per_interval
    torch.set_num_threads(1)
    venv = VecNormalize(DrawnPlants(dist, config), norm_obs=False, norm_reward=True,
                        gamma=a.gamma)
    model = PPO("MlpPolicy", venv, n_steps=a.n_steps, batch_size=1024, n_epochs=4,
                learning_rate=a.lr, gamma=a.gamma, clip_range=a.clip, target_kl=a.target_kl,
                seed=a.seed, device="cpu", verbose=0,
                policy_kwargs={"net_arch": {"pi": list(config.hidden), "vf": list(config.hidden)},
                               "activation_fn": torch.nn.Tanh})
    start = time.monotonic()
    if init is not None:
        actor = actor_layers(model)
        copy_layers(actor, [m for m in init.net if isinstance(m, torch.nn.Linear)])
        if a.warmup:  # the critic alone: the actor's weights get no gradient
            actor_params = [q for m in actor for q in m.parameters()]
            for q in actor_params:
                q.requires_grad_(False)
            model.learn(total_timesteps=a.warmup)
            for q in actor_params:
                q.requires_grad_(True)
    model.learn(total_timesteps=steps, reset_num_timesteps=not a.warmup)
    seconds = time.monotonic() - start
    student = student_record(model, config)
    states = model.rollout_buffer.observations.reshape(-1, venv.observation_space.shape[0])
    sb3 = model.predict(states, deterministic=True)[0].astype(np.int64)
    if config.head == "joint":  # PPO's setting number, as valves
        sb3 = SETTINGS[sb3.reshape(-1)]
    mismatch = int((HistoryPolicy.from_record(student).act(states) != sb3).any(axis=1).sum())
    if mismatch:  # the transplant must act as PPO's own deterministic policy
        print(f"adaptive_rl: error: the student's layout acts otherwise than PPO on "
              f"{mismatch} of {len(states)} states", file=sys.stderr)
        return 1
    record = {"policy": student, "snapshots": [], "curve": [],
              "config": {**config.to_json(), "ppo_steps": int(model.num_timesteps),
                         "init": a.init, "warmup": a.warmup, "lr": a.lr, "gamma": a.gamma,
                         "clip": a.clip, "target_kl": a.target_kl},
              "distribution": dist.text, "train_seconds": seconds,
              "load_average": os.getloadavg()}
    try:
        atomic_torch_save(a.out, record)
    except OSError as e:
        print(f"adaptive_rl: error: cannot write {a.out}: {e}", file=sys.stderr)
        return EXIT_STORAGE
    print(f"adaptive_rl: {model.num_timesteps} steps in {seconds:.0f} s, {a.out} (acts as PPO's "
          f"deterministic policy on its last rollout's {len(states)} states)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
