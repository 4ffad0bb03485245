"""learning/torch_startup.py: torch.optim no longer imports torch._dynamo (2 s of
start-up) for optimisers that only hold state, and the arithmetic is untouched.
Each case runs in a fresh interpreter, since an import cannot be undone."""

from __future__ import annotations

import subprocess
import sys

import pytest

# A native-engine PPO's life: built, acting, a native update (Adam's moments read from
# and written to the torch optimiser), its optimiser reset, saved and loaded.
NATIVE_ENGINE = """
import sys, torch
from ftc.learning.ppo import PPO, PPOConfig
from ftc.learning.buffer import RolloutBatch
from ftc.learning.ppo_native import flat_ppo_update
ppo = PPO(PPOConfig(engine="native"), seed=0)
obs = torch.rand(32, 6, generator=torch.Generator().manual_seed(1))
actions, logprobs, values = ppo.act(obs)
batch = RolloutBatch(obs, actions, logprobs, values, torch.randn(32), values)
flat_ppo_update(ppo.policy, ppo.optimizer, batch, ppo.config, ppo.generator)
ppo.reset_optimizer()
ppo.optimizer.load_state_dict(ppo.optimizer.state_dict())
ppo.optimizer.zero_grad()
print("torch._dynamo" in sys.modules)
"""

# A torch-engine update; its weights' bytes, with torch's own wrappers (torch._dynamo
# imported first, so nothing is marked) and with the marked ones.
TORCH_UPDATE = """
import sys, hashlib, torch
if sys.argv[1] == "dynamo-first":
    import torch._dynamo
from ftc.learning.ppo import PPO, PPOConfig
from ftc.learning.torch_startup import skip_dynamo_import
print(skip_dynamo_import() > 0)
from ftc.learning.buffer import RolloutBatch
ppo = PPO(PPOConfig(engine="torch"), seed=0)
obs = torch.rand(32, 6, generator=torch.Generator().manual_seed(1))
actions, logprobs, values = ppo.act(obs)
batch = RolloutBatch(obs, actions, logprobs, values, torch.randn(32, generator=torch.Generator().manual_seed(2)), values)
from ftc.learning.ppo import ppo_update
ppo_update(ppo.policy, ppo.optimizer, batch, ppo.config, ppo.generator)
h = hashlib.sha256()
for p in ppo.policy.parameters():
    h.update(p.detach().numpy().tobytes())
print(h.hexdigest())
"""


def _python(code: str, *args: str) -> list[str]:
    return subprocess.run([sys.executable, "-c", code, *args], check=True,
                          capture_output=True, text=True).stdout.split()


def test_a_numpy_engine_ppo_never_imports_dynamo():
    assert _python(NATIVE_ENGINE) == ["False"]


@pytest.mark.slow  # 10-30 s: the fresh-clone CI stays under its 10 minutes
def test_torch_updates_are_bit_identical_with_and_without_the_marks():
    marked, marked_weights = _python(TORCH_UPDATE, "marked")
    unmarked, plain_weights = _python(TORCH_UPDATE, "dynamo-first")
    assert (marked, unmarked) == ("True", "False")  # the two paths really differ
    assert marked_weights == plain_weights
