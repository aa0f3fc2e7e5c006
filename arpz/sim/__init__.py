"""The 2-D simulator that stands in for Gazebo (seed 001 section 3.2), in pure numpy.

A robot process runs a ``RobotBody`` in a ``World`` on a ``SimClock``; the CEDDP runs the hallway
planner (``arpz.ceddp.hallway``) and the ``Judge``. ``arpz.sim.offline.run_offline`` closes the
loop without a network for tests. docs/simulation.md describes the whole mission.
"""

from arpz.sim.body import RobotBody
from arpz.sim.clock import ManualTime, SimClock
from arpz.sim.judge import Judge, JudgeSettings, MissionResult
from arpz.sim.kinematics import Pose, integrate
from arpz.sim.lidar import BEAM_ANGLES_DEG, Lidar, beam_endpoints, beam_of_topic, beam_topic
from arpz.sim.mission import STOP, MissionEvent, VelocityCommand
from arpz.sim.world import MapError, Obstacle, World

__all__ = [
    "BEAM_ANGLES_DEG",
    "STOP",
    "Judge",
    "JudgeSettings",
    "Lidar",
    "ManualTime",
    "MapError",
    "MissionEvent",
    "MissionResult",
    "Obstacle",
    "Pose",
    "RobotBody",
    "SimClock",
    "VelocityCommand",
    "World",
    "beam_endpoints",
    "beam_of_topic",
    "beam_topic",
    "integrate",
]
