"""The command lines: the interval runs (controller, mpc, plugin, with what
they share in :mod:`ftc.tools.run_cli`), and the tools around the plant:
simulate (trajectory export with a fixed valve policy), relay (a lossy LCM
relay for fault injection), replay (a recorded LCM log read back into a
trajectory), export (a trained policy to ONNX for the embedded side) and
policy_weights. Each is also reachable as ``python -m ftc.<tool>``."""
