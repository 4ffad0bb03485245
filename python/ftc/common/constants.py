"""Named constants of the plant and the wire, defined once
(``docs/plant-model.md`` for the physics)."""

from __future__ import annotations

NUM_TANKS = 6
NUM_VALVES = NUM_TANKS  # one valve per tank, on the shared conduit
NUM_ENGINES = 2
TANK_HEIGHT = 1.0  # m, nominal h_i of every tank; model predictions are clipped to it

# m^3: a plant with less fuel than this counts as empty (cg = sigma = 0 in the reward)
EMPTY_VOLUME = 1e-6
# m^3: an episode is terminal once volume < one step of engine demand + this
# (in favour of ending, as the plant's rule; larger than any integration error)
TERMINAL_TOLERANCE = 1e-6

# The plant's default bus: loopback only (ttl=0). Runs use a private port and prefix.
DEFAULT_LCM_URL = "udpm://239.255.76.67:7667?ttl=0"
LCM_MULTICAST_GROUP = "239.255.76.67"
DEFAULT_PREFIX = "FTC_"


def pretrain_seed(seed: int) -> int:
    """Seed of the simulated plants (or model rollouts) of nominal pretraining."""
    return seed * 1000 + 17


def offline_seed(seed: int, interval: int) -> int:
    """Seed of interval ``interval``'s offline phase (model rollouts and PPO's
    generator): reproducible in whichever process the phase runs."""
    return seed * 7919 + interval
