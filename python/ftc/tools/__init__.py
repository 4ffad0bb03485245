"""Command-line tools around the plant: simulate (trajectory export with a
fixed valve policy), relay (a lossy LCM relay for fault injection) and replay
(a recorded LCM log read back into a trajectory) and export (a trained policy
to ONNX for the embedded side). Each is also reachable as
``python -m ftc.<tool>``."""
