"""How a run goes: the Agent protocol, the interval runner and its loops
(lockstep, real time, learning off the loop), checkpoints, metrics.csv,
TensorBoard and the policy push. Knows no method."""
