"""Receding-horizon planners and their evaluators; ``physics/`` holds those on
the plant's equations (the C++ core's rollouts, the episode planner)."""
