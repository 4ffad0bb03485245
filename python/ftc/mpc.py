"""``python -m ftc.mpc``: the MPC reference controllers (:mod:`ftc.control.mpc_cli`)."""

import sys

from ftc.control.mpc_cli import main

if __name__ == "__main__":
    sys.exit(main())
