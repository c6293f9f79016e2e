"""System interfaces (Plant, ClosedLoopSystem), the PD position controller and the built-in simulator."""

from efficienttrack.systems.pd import XE75_PD, ClosedLoop, PDGains
from efficienttrack.systems.protocol import BatchedSystem, ClosedLoopSystem, Plant, check_system
from efficienttrack.systems.spec import SystemSpec, load_plant, load_system

__all__ = [
    "XE75_PD",
    "BatchedSystem",
    "ClosedLoop",
    "ClosedLoopSystem",
    "PDGains",
    "Plant",
    "SystemSpec",
    "check_system",
    "load_plant",
    "load_system",
]
