"""The plant as the controller sees it: observations, the :class:`PlantLink`
protocol and its links (the real process over LCM, the core in process),
reward, recorded logs, the trajectory schema and the Gymnasium env.

The names most code needs are re-exported here (``from ftc.plant import
launch, CorePlant``); each lives in its own module.
"""

from ftc.common.constants import DEFAULT_LCM_URL, DEFAULT_PREFIX, NUM_ENGINES, NUM_TANKS
from ftc.plant.lcm_link import (LcmPlant, LinkConfig, attach, check_loopback_url, launch,
                                private_lcm_url, private_prefix)
from ftc.plant.link import (CorePlant, PlantError, PlantGoneError, PlantLink, PlantObservation,
                            valves_array)

__all__ = ["DEFAULT_LCM_URL", "DEFAULT_PREFIX", "NUM_ENGINES", "NUM_TANKS", "CorePlant",
           "LcmPlant", "LinkConfig", "PlantError", "PlantGoneError", "PlantLink",
           "PlantObservation", "attach", "check_loopback_url", "launch", "private_lcm_url",
           "private_prefix", "valves_array"]
