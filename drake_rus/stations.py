"""``MakeStation``: the one place that picks the simulated or the hardware station.

Both export the same ports (docs/design.md), so everything above this module (the scan, the
controller, the studies) is built once and never knows which one it drives. The two stations
never import each other; like Drake's hardware_sim, this dispatcher chooses from the
scenario's ``hardware`` flag.
"""

from __future__ import annotations

from pydrake.geometry import Meshcat
from pydrake.systems.framework import Diagram

from drake_rus.hardware.station import MakeHardwareStation
from drake_rus.scenario import CheckScenario, Scenario
from drake_rus.station import MakeSimStation

__all__ = ["MakeStation"]


def MakeStation(
    scenario: Scenario, meshcat: Meshcat | None = None, *, patient=None, name: str = "station"
) -> Diagram:
    """The station for ``scenario.hardware``: simulated (false) or the real robot (true).

    ``patient`` applies to simulation only (the real patient lies on the real bed)."""
    CheckScenario(scenario)
    if scenario.hardware:
        return MakeHardwareStation(scenario, meshcat=meshcat, name=name)
    return MakeSimStation(scenario, meshcat=meshcat, patient=patient, name=name)
