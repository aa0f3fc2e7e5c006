"""The CEDDP server: Zenoh router, cache control, planner, optimisers, Rerun dashboard.

The public API of the server: ``CeddpServer`` (run by ``python -m arpz.ceddp``, or embedded),
the planner a team extends (``Planner``, the ``Reading`` it gets and the ``PlannerCommands`` it
sends through; docs/nodes.md) and the QoS balancing optimiser of seed 001 (``solve``,
``assign_qos`` and their inputs and errors). The dashboard (``arpz.ceddp.dashboard``, the one
module that imports Rerun) is not imported here, so that the server can run without it.
Everything else is internal.
"""

from arpz.ceddp.optimiser import (
    InfeasibleQosError,
    InvalidQosInput,
    LinkQuality,
    OptimiserError,
    QosAssignment,
    QosLimits,
    QosSolution,
    assign_qos,
    solve,
)
from arpz.ceddp.planner import Planner, PlannerCommands, Reading
from arpz.ceddp.server import CeddpServer

__all__ = [
    "CeddpServer",
    "InfeasibleQosError",
    "InvalidQosInput",
    "LinkQuality",
    "OptimiserError",
    "Planner",
    "PlannerCommands",
    "QosAssignment",
    "QosLimits",
    "QosSolution",
    "Reading",
    "assign_qos",
    "solve",
]
