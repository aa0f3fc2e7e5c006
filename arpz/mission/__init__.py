"""The mission in one place, owned by neither the robot nor the CEDDP: the 2-D world that stands
in for Gazebo (seed 001 section 3.2, pure numpy), the vocabulary of commands and events, the
hallway planner and the judge.

A robot process runs a ``RobotBody`` in a ``World`` on a ``SimClock``; the CEDDP runs the hallway
planner (``arpz.mission.hallway``) and the ``Judge``. ``arpz.mission.offline.run_offline`` closes
the loop without a network for tests. docs/simulation.md describes the whole mission.
"""

from arpz.mission.body import RobotBody
from arpz.mission.clock import ManualTime, SimClock
from arpz.mission.judge import Judge, JudgeSettings, MissionResult
from arpz.mission.kinematics import Pose, integrate
from arpz.mission.lidar import BEAM_ANGLES_DEG, Lidar, beam_endpoints, beam_of_topic, beam_topic
from arpz.mission.vocabulary import STOP, MissionEvent, VelocityCommand
from arpz.mission.world import MapError, Obstacle, World

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
