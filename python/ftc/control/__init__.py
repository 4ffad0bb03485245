"""Control, in rooms: ``run/`` (the interval runner and its loops, checkpoints,
metrics), ``planning/`` (planners and their evaluators), ``agents/`` (one
module per method family) and :mod:`ftc.control.registry` (the methods, as
data). Their command lines are in :mod:`ftc.tools`. See docs/architecture.md."""
