"""The QoS profile of every kind of traffic between robots and the CEDDP (docs/protocol.md).

arpz promises that nothing is lost silently in either direction, so every key a robot or the
CEDDP writes goes through the reliable channel with a declared profile, and each side of a key
uses the same one (both ends are configured from the same five fields). The defaults are chosen
for what the traffic is for:

- sensors: RELIABLE KEEP_LAST 10, the ROS 2 default; the QoS optimiser retunes the depth.
- hello: the Hello round-trip probe of seed 001 Fig. 9 is "one more topic" in the paper, so its
  four hops (two up, two down) use the sensor profile unless ``hello_qos`` is given.
- commands: RELIABLE KEEP_LAST 10 with a lifespan of 0.5 s: a command that arrives later than that
  (a link outage) is dropped and counted, never applied late to a moving robot.
- assignment: RELIABLE TRANSIENT_LOCAL KEEP_LAST 1, a "latched" topic: a robot that joins or
  reconnects receives the assignment in force, also after a link outage.
- frames (camera frames, point clouds): RELIABLE KEEP_LAST 1 *frame*, counted in frames: the
  newest frame wins, an older one still incomplete is dropped and counted; each frame travels as
  fragments of one radio frame, and only missing fragments are resent (docs/reliability.md).
- reports (stats, announcements, QoS acks, telemetry, the CEDDP's stats): RELIABLE, and
  TRANSIENT_LOCAL KEEP_LAST 4 so a restarted CEDDP learns each robot's latest report at once;
  a robot waits for the final report's acknowledgement before it closes.

``reliability = "none"`` in a config turns all of it off (plain Zenoh puts, loss still counted
from sequence numbers); it must be set on both sides, and a pair that disagrees is reported as
INCOMPATIBLE_QOS on both.
"""

from __future__ import annotations

from typing import Final, Literal

from arpz.core.protocol.qos import DurabilityPolicy, QosProfile

#: "channel": every key through the reliable channel; "none": plain Zenoh puts (asked for only)
ChannelMode = Literal["channel", "none"]
CHANNEL_MODES: Final = ("channel", "none")

SENSOR_QOS: Final = QosProfile()
COMMAND_QOS: Final = QosProfile(depth=10, lifespan_s=0.5)
ASSIGNMENT_QOS: Final = QosProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL)
REPORT_QOS: Final = QosProfile(depth=4, durability=DurabilityPolicy.TRANSIENT_LOCAL)
FRAMES_QOS: Final = QosProfile(depth=1)
