"""Learning: PPO (policy, buffer, the one rollout collector), the world model
and the env built on it, nominal pretraining and the offline phase. Knows the
plant only through :mod:`ftc.plant`; knows nothing of runs or experiments."""
