"""Fault-tolerant control of a degrading aircraft fuel-transfer plant with RL.

In a checkout the package's build products (the LCM message classes generated
by ``lcm-gen``, the ``_core`` and ``_learn`` bindings, the plant program) live
in the CMake build tree, never in the source tree; they are made importable
as ``ftc.<name>`` here. Set ``FTC_BUILD_DIR`` to use a build directory other
than ``<repo>/build``. Installed with ``pip install .``, they are inside the
package (the programs in ``ftc/bin``). :func:`plant_binary` finds the plant
either way.
"""

from __future__ import annotations

import os
from pathlib import Path

# One BLAS thread, as one torch thread (control/ppo_agent.py): the networks here are
# tiny, and OpenBLAS's second thread spins against the other runs on a shared
# machine (measured: a policy's forward + backward pass on 128 states 1.6 ms with
# one thread, 8.9 ms with two beside a 2-job benchmark). It also makes results
# independent of the core count (sgemm's sums are split by thread). Set before
# NumPy is first imported; an explicit OPENBLAS_NUM_THREADS wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from ftc.common.paths import BUILD_DIR, PACKAGE_DIR, REPO_ROOT  # noqa: E402,F401

# ftc.plant_binary(): the plant program, in a checkout's build/ or installed
from ftc.common.build_info import plant_binary  # noqa: E402,F401

for _generated in (BUILD_DIR / "lcmtypes" / "ftc", BUILD_DIR / "python"):
    if _generated.is_dir() and str(_generated) not in __path__:
        __path__.append(str(_generated))


def _register_envs() -> None:
    """Register the Gymnasium ids (entry-point strings only: the env module, the
    plant link and matplotlib are imported when an env is made, not here).

    Gymnasium 1.x no longer loads ``gymnasium.envs`` entry-point plugins, so the
    ids exist once ``ftc`` is imported: by ``import ftc`` (any ftc module), or by
    gymnasium itself for the module-prefixed id ``"ftc:ftc/FuelTransfer-v0"``.
    max_episode_steps=512 is the paper's t_online, one degradation interval
    (scenarios/*.toml: steps_per_interval): the plant cuts off the episode that
    is running at an interval boundary itself, so no episode is longer, and the
    time limit is a backstop that never ends an episode the plant would not.
    ``gym.make_vec(id, num_envs=N, vectorization_mode="vector_entry_point")``
    gives the batched C++ pool (ftc.plant.vector) for either id.
    """
    import gymnasium

    for env_id, link in (("ftc/FuelTransfer-v0", "lcm"), ("ftc/FuelTransferCore-v0", "core")):
        if env_id not in gymnasium.registry:  # a reload of ftc must not warn about overriding
            gymnasium.register(id=env_id, entry_point="ftc.plant.env:FuelTransferEnv",
                               vector_entry_point="ftc.plant.vector:make_vector",
                               kwargs={"scenario": "single", "link": link},
                               max_episode_steps=512)


_register_envs()
