"""FOSS, the first-order shelf simulator (Ch. 9.5.1): deterministic quasi-static blade pushes and
suction pick-and-place of extruded footprints on the shelf floor, and the target's visibility."""

from ms_drake.foss.simulator import (  # noqa: F401
    SUCTION_GRID,
    SUCTION_LIFTS,
    VISIBILITY_THRESHOLD,
    Foss,
    FossParams,
    shelf_action,
)
from ms_drake.foss.system import FossSystem  # noqa: F401
