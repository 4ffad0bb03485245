"""The lockstep link survives a lossy, duplicating transport: every lost
message is retried, no step is applied twice, and the trajectory is identical
to the in-process core's."""

from __future__ import annotations

import json
import signal
import subprocess
import sys

import numpy as np

from ftc.common.build_info import plant_binary
from ftc.plant import CorePlant, LcmPlant, LinkConfig, private_lcm_url, private_prefix


def test_lockstep_through_a_lossy_relay_matches_the_lossless_trajectory(scenarios):
    scenario = str(scenarios / "single.toml")
    url, client, plant_prefix = private_lcm_url(), private_prefix(), private_prefix()
    plant = subprocess.Popen([str(plant_binary()), "--lcm-url", url, "--prefix", plant_prefix,
                              "--scenario", scenario, "--steps-per-interval", "100"])
    relay = subprocess.Popen([sys.executable, "-m", "ftc.relay", "--lcm-url", url,
                              "--client-prefix", client, "--plant-prefix", plant_prefix,
                              "--loss", "0.1", "--duplicate", "0.1", "--seed", "7"],
                             stdout=subprocess.PIPE, text=True)
    try:
        assert relay.stdout.readline().strip() == "ready"
        link = LcmPlant(url, client, config=LinkConfig(retry_timeout=0.03, give_up_timeout=5))
        core = CorePlant(scenario, 0, steps_per_interval=100)
        rng = np.random.default_rng(0)
        link.reset(), core.reset()
        for _ in range(300):
            u = rng.integers(0, 2, 6)
            a, b = link.step(u), core.step(u)
            # exact: a retried command must not step the plant twice
            np.testing.assert_array_equal(a.true_level, b.true_level)
            assert (a.step, a.episode, a.age) == (b.step, b.episode, b.age)
            if a.done:
                link.reset(), core.reset()
        assert link.retries > 0  # losses happened and were recovered
        assert link.last_state.duplicate_commands > 0  # duplicates reached the plant
        link.close()
    finally:
        relay.send_signal(signal.SIGTERM)
        out, _ = relay.communicate(timeout=5)
        plant.terminate()
        plant.wait(timeout=5)
    counts = json.loads(out.strip().splitlines()[-1])
    # 10% loss over >= 600 messages: tens of drops expected
    assert counts["dropped"] >= 20 and counts["duplicated"] >= 20
