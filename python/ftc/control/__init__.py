"""Control: the interval runner (:mod:`ftc.control.runner`) and the agents it
drives (baselines, PPO as in Algorithm 1, MPC oracle, MPC on the learned
model), their configs and command lines. See docs/architecture.md."""
