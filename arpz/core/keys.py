"""Zenoh key expressions of an arpz fleet, in one place.

Every key lives under ``arpz/{fleet}/`` so that several fleets can share a router and so that
access control can grant a robot exactly ``arpz/{fleet}/robot/{robot}/**`` (less its ``cmd``
subtree). docs/protocol.md is the user-facing description; keep the two in step.

Robot and topic names are single key chunks: lowercase letters, digits, ``_`` and ``-``.
"""

from __future__ import annotations

import re

from arpz.core.errors import ArpzError

ROOT = "arpz"
_CHUNK = re.compile(r"^[a-z0-9][a-z0-9_\-]*$")


class KeyExprError(ArpzError, ValueError):
    """A name that cannot be used as a single Zenoh key chunk."""


def check_chunk(name: str, *, what: str) -> str:
    """Return ``name`` if it is a valid single chunk, else raise saying how to fix it."""
    if not _CHUNK.match(name):
        raise KeyExprError(
            f"{what} {name!r} is not a valid key chunk: use lowercase letters, digits, '_' or '-', "
            "starting with a letter or digit (no '/', '*', '$', '?', '#' or spaces)"
        )
    return name


_PARTITION = re.compile(r"^(\*|[a-z0-9_\-]*(\$\*[a-z0-9_\-]*)+|[a-z0-9][a-z0-9_\-]*)$")


def check_partition(pattern: str) -> str:
    """A robot-id pattern for one key chunk: "*", an id, or ids with Zenoh's ``$*`` wildcard
    ("east-$*" = every robot whose id starts with "east-")."""
    if not _PARTITION.match(pattern):
        raise KeyExprError(
            f"partition {pattern!r} must be '*', a robot id, or a pattern with '$*' such as "
            "'east-$*' (lowercase letters, digits, '_' and '-')"
        )
    return pattern


def fleet_prefix(fleet: str) -> str:
    return f"{ROOT}/{check_chunk(fleet, what='fleet')}"


def robot_prefix(fleet: str, robot: str) -> str:
    return f"{fleet_prefix(fleet)}/robot/{check_chunk(robot, what='robot id')}"


def sensor_key(fleet: str, robot: str, topic: str) -> str:
    """Sensor readings of one topic of one robot (robot -> CEDDP)."""
    return f"{robot_prefix(fleet, robot)}/sensor/{check_chunk(topic, what='topic')}"


def frames_key(fleet: str, robot: str, topic: str) -> str:
    """Large samples (camera frames, point clouds) of one topic, as the reliable channel's
    fragments (robot -> CEDDP); the reassembled payload is a ``Sample`` as on ``sensor/``."""
    return f"{robot_prefix(fleet, robot)}/frames/{check_chunk(topic, what='topic')}"


#: the Hello probe's name both ways (seed 001 Fig. 9): the robot's ``sensor/hello`` up, each
#: robot's ``cmd/hello`` down
HELLO = "hello"


def command_key(fleet: str, robot: str, name: str) -> str:
    """Commands for one robot's actuation (CEDDP -> robot)."""
    return f"{robot_prefix(fleet, robot)}/cmd/{check_chunk(name, what='command')}"


def service_key(fleet: str, robot: str, name: str) -> str:
    """One of a robot's services (a Zenoh query from a caller, answered by the robot:
    ``ServiceRequest`` in, ``ServiceReply`` out; docs/protocol.md "Services")."""
    return f"{robot_prefix(fleet, robot)}/srv/{check_chunk(name, what='service')}"


def robot_services(fleet: str, robot: str) -> str:
    """Every service of one robot: the one queryable a robot declares for all of them (so that
    a name it does not serve is answered, not left to time out)."""
    return f"{robot_prefix(fleet, robot)}/srv/*"


def all_services(fleet: str) -> str:
    return f"{fleet_prefix(fleet)}/robot/*/srv/*"


def presence_key(fleet: str, robot: str) -> str:
    """Liveliness token of a running robot agent."""
    return f"{robot_prefix(fleet, robot)}/presence"


def robot_mode_key(fleet: str, robot: str, mode: str) -> str:
    """Liveliness token saying how the robot exchanges data: "channel" (the reliable channel) or
    "none" (plain puts). The CEDDP compares it with its own mode (INCOMPATIBLE_QOS if not equal)."""
    return f"{robot_prefix(fleet, robot)}/mode/{check_chunk(mode, what='mode')}"


def stats_key(fleet: str, robot: str) -> str:
    """Periodic counters reported by a robot (produced, sent, held back, Hello round trips)."""
    return f"{robot_prefix(fleet, robot)}/stats"


def telemetry_key(fleet: str, robot: str) -> str:
    """A simulated robot's true pose (judging and drawing only; the planner never reads it)."""
    return f"{robot_prefix(fleet, robot)}/telemetry"


def announce_key(fleet: str, robot: str) -> str:
    """What a robot publishes and subscribes to (its topics), re-sent periodically."""
    return f"{robot_prefix(fleet, robot)}/announce"


def qos_ack_key(fleet: str, robot: str) -> str:
    """A robot's answer (applied / refused) to the CEDDP's QoS assignment."""
    return f"{robot_prefix(fleet, robot)}/qos"


def ceddp_qos_request_key(fleet: str) -> str:
    """Any put here asks the CEDDP to run the QoS optimiser again now."""
    return f"{fleet_prefix(fleet)}/ceddp/qos/request"


def ceddp_presence_key(fleet: str) -> str:
    """Liveliness token of the CEDDP server."""
    return f"{fleet_prefix(fleet)}/ceddp/presence"


def ceddp_mode_key(fleet: str, mode: str) -> str:
    """Liveliness token of the CEDDP's mode ("channel" or "none"), compared by every robot."""
    return f"{fleet_prefix(fleet)}/ceddp/mode/{check_chunk(mode, what='mode')}"


def all_ceddp_modes(fleet: str) -> str:
    return f"{fleet_prefix(fleet)}/ceddp/mode/*"


def ceddp_stats_key(fleet: str) -> str:
    """Periodic CPU and per-topic arrival rates of the CEDDP process."""
    return f"{fleet_prefix(fleet)}/ceddp/stats"


def ceddp_clock_key(fleet: str) -> str:
    """The CEDDP's clock, as a Zenoh queryable: a robot's ``ClockRequest`` gets a
    ``ClockReply`` (the NTP-style exchange of arpz/core/protocol/clock.py)."""
    return f"{fleet_prefix(fleet)}/ceddp/clock"


def ceddp_commands_key(fleet: str) -> str:
    """What the CEDDP's planners send, as a Zenoh queryable: a robot asks at start-up
    (``CommandContract``) and refuses to start when it would get a command type its actuator
    does not take."""
    return f"{fleet_prefix(fleet)}/ceddp/commands"


def ceddp_qos_key(fleet: str) -> str:
    """QoS assignment published by the CEDDP's balancing optimiser."""
    return f"{fleet_prefix(fleet)}/ceddp/qos"


def ceddp_config_key(fleet: str) -> str:
    """A configurator's solution (seed 002), applied by the robots: ``python -m arpz.configure
    apply`` publishes it."""
    return f"{fleet_prefix(fleet)}/ceddp/config"


def config_ack_key(fleet: str, robot: str) -> str:
    """A robot's answer to a configuration; two chunks below the robot, so the CEDDP's report
    subscription (``robot/*/*``) does not take it for a report."""
    return f"{robot_prefix(fleet, robot)}/config/ack"


def all_config_acks(fleet: str) -> str:
    return f"{fleet_prefix(fleet)}/robot/*/config/ack"


# Wildcards used by the CEDDP to see the whole fleet.
def all_sensors(fleet: str, partition: str = "*") -> str:
    return f"{fleet_prefix(fleet)}/robot/{check_partition(partition)}/sensor/*"


def all_frames(fleet: str, partition: str = "*") -> str:
    return f"{fleet_prefix(fleet)}/robot/{check_partition(partition)}/frames/*"


def all_presence(fleet: str) -> str:
    return f"{fleet_prefix(fleet)}/robot/*/presence"


def all_robot_modes(fleet: str) -> str:
    return f"{fleet_prefix(fleet)}/robot/*/mode/*"


def all_reports(fleet: str) -> str:
    """Every robot's reports (stats, announce, qos acks, telemetry): one chunk below the robot."""
    return f"{fleet_prefix(fleet)}/robot/*/*"


def all_stats(fleet: str) -> str:
    return f"{fleet_prefix(fleet)}/robot/*/stats"


def all_announce(fleet: str) -> str:
    return f"{fleet_prefix(fleet)}/robot/*/announce"


def parse_robot_key(key: str) -> tuple[str, str, str] | None:
    """Split ``arpz/{fleet}/robot/{robot}/{kind}[/{name}]`` into (robot, kind, name).

    Returns None for any key outside that shape, so a caller can count it as unknown instead of
    crashing on it. ``name`` is "" for keys without one (presence, stats, announce).
    """
    parts = key.split("/")
    if len(parts) < 5 or parts[0] != ROOT or parts[2] != "robot":
        return None
    robot, kind = parts[3], parts[4]
    if len(parts) == 5:
        return robot, kind, ""
    if len(parts) == 6:
        return robot, kind, parts[5]
    return None
