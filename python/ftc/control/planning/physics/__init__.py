"""Planning on the plant's equations: evaluators on the C++ physics, the true
physics stepped by the episode planner."""
