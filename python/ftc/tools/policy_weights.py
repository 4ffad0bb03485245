"""``python -m ftc.tools.policy_weights push``: push a weights file to a running
policy node (the format and the message: :mod:`ftc.control.run.policy_weights`).

    python -m ftc.tools.policy_weights push policy.txt --version 2 --lcm-url ... --prefix RT_

It waits for the node's answer: exit 0 when the node flies the weights, 1
with one line naming the reason when it rejected them or did not answer. A
file with a history window (``ftc-policy 2``, the adaptive student) goes out
as a ``policy_v2_t``, one of the levels (``ftc-policy 1``) as a ``policy_t``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Sequence

from ftc.common.cli import OneLineParser, at_least, checked, positive
from ftc.common.errors import EXIT_FAILURE, UsageError
from ftc.plant.signing import load_key
from ftc.control.run.policy_weights import (actions, actor_layers, checksum, format_weights,  # noqa: F401
                                        policy_message, push, read_policy, read_weights,
                                        student_layers, window_inputs, write_weights)


def main(argv: Sequence[str] | None = None) -> int:
    parser = OneLineParser(prog="python -m ftc.tools.policy_weights",
                           description=__doc__.split("\n\n")[0],
                           formatter_class=argparse.RawDescriptionHelpFormatter,
                           epilog=__doc__.split("\n\n", 1)[1])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("push", help="push a weights file to a running policy node")
    p.add_argument("weights", type=checked(Path, nonempty=True), help="a weights file")
    p.add_argument("--version", type=checked(int, at_least(1, 2**62)),
                   help="the version to push as (default: the file's)")
    p.add_argument("--lcm-url", required=True, help="the node's LCM URL (ttl=0)")
    p.add_argument("--prefix", default="FTC_", help="the node's channel prefix")
    p.add_argument("--timeout", type=checked(float, positive(3600.0)), default=2.0,
                   help="seconds to wait for the node's answer")
    p.add_argument("--key-file", type=checked(Path, nonempty=True), default=None,
                   help="sign the push with the node's key (hex, mode 600)")
    args = parser.parse_args(argv)
    try:
        key = load_key(args.key_file) if args.key_file else None
        w = read_policy(args.weights)
        outcome = push(args.lcm_url, args.prefix,
                       policy_message(w.widths, w.params, args.version or w.version,
                                      window=w.window, stuck_memory=w.stuck_memory),
                       args.timeout, key=key)
    except (UsageError, ValueError) as e:
        parser.error(str(e))
    if not outcome.accepted:
        print(f"policy_weights: error: {args.weights} on {args.prefix}POLICY: "
              f"{outcome.describe()}", file=sys.stderr)
        return EXIT_FAILURE
    print(f"policy_weights: pushed {args.weights} as version {outcome.version} "
          f"on {args.prefix}POLICY: accepted")
    return 0


if __name__ == "__main__":
    sys.exit(main())
