"""Keep torch.optim from importing torch._dynamo when nothing is compiled.

torch.optim's ``Optimizer.__init__``, ``state_dict``, ``load_state_dict``,
``zero_grad`` and ``add_param_group`` are wrapped by ``torch._disable_dynamo``,
which imports ``torch._dynamo`` (and sympy) on the first call to find its
"disabled" version of the function: 2.0 s of every controller's start-up on
this machine, though nothing here is ever compiled. The wrapper caches that
version on the function as ``__dynamo_disable``; :func:`skip_dynamo_import`
caches the function itself there, which is what the disabled version calls
when nothing compiles. The arithmetic is untouched.

Adam's ``step`` imports ``torch._dynamo`` itself, so runs that step a torch
optimiser (the torch PPO engine, the torch world-model trainer) still pay the
import on their first update; runs whose optimiser only holds state (the native
PPO engine) no longer do. Measured: a native-engine PPO built in 0.10 s
instead of 2.0 s; its 10-interval run 8.7 s (scripts/bench.py,
``ppo_run_core_native_ppo_s``).
"""

from __future__ import annotations

import sys

import torch
import torch._compile


def skip_dynamo_import() -> int:
    """Mark torch.optim's dynamo-disabled methods as already resolved; returns
    how many were marked (0 if this torch wraps them differently: then the
    import simply happens as before)."""
    if "torch._dynamo" in sys.modules:
        return 0  # already paid for; keep torch's own wrappers
    inner = torch._compile._disable_dynamo(lambda: None).__code__
    marked = 0
    for cls in (torch.optim.Optimizer, *torch.optim.Optimizer.__subclasses__()):
        for f in vars(cls).values():
            if getattr(f, "__code__", None) is inner and hasattr(f, "__wrapped__"):
                setattr(f.__wrapped__, "__dynamo_disable", f.__wrapped__)
                marked += 1
    return marked
