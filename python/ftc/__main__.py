"""``python -m ftc``: the package's version and its command-line tools.

    python -m ftc --version
"""

from __future__ import annotations

import argparse
import sys
from typing import Sequence

from ftc.common.build_info import ftc_version

TOOLS = (
    ("ftc.controller", "PPO (the paper's Algorithm 1, ppo-robust, ppo-learned) and the baselines"),
    ("ftc.mpc", "the MPC controllers: oracle-mpc, reference, model-mpc, learned-mpc, "
                "identified-mpc"),
    ("ftc.experiments", "the paper's experiments, the benchmark suite, compare"),
    ("ftc.export", "a trained policy as ONNX and as the embedded node's weights"),
    ("ftc.replay", "replay a recorded run"),
    ("ftc.plugin", "score your own controller (module:factory, sb3:PATH.zip, onnx:PATH.onnx)"),
)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m ftc", description="Fault-tolerant control of degrading systems with "
        "reinforcement learning. The tools (each with --help):\n\n" + "\n".join(
            f"  python -m {name:<16} {what}" for name, what in TOOLS),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--version", action="version", version=f"ftc {ftc_version()}")
    parser.parse_args(argv)
    parser.print_help()
    return 0


if __name__ == "__main__":
    sys.exit(main())
