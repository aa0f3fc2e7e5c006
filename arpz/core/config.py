"""Configuration of robots and of the CEDDP: msgspec Structs loaded from TOML.

Unknown fields are errors (a typo in a TOML file must not be silently ignored), and every error
names the file, the field and what is wrong, so ``python -m arpz.robot`` can exit with code 2 and
a message the user can act on.
"""

from __future__ import annotations

import math
import re
import tomllib
from pathlib import Path
from typing import Any, Final, Literal, TypeVar

import msgspec

from arpz.core import keys
from arpz.core.endpoints import check_endpoints
from arpz.core.errors import ConfigError as ConfigError  # re-exported: callers catch it from here
from arpz.core.protocol.fragments import MAX_FRAGMENT_BYTES
from arpz.core.protocol.qos import QosProfile
from arpz.core.traffic import (
    ASSIGNMENT_QOS,
    COMMAND_QOS,
    FRAMES_QOS,
    REPORT_QOS,
    SENSOR_QOS,
    ChannelMode,
)

SensorKind = Literal[
    "lidar",
    "dht11",
    "imu",
    "ultrasonic",
    "flame",
    "pir",
    "light",
    "camera",
    "pointcloud",
    "message",
]
SENSOR_KINDS: tuple[str, ...] = (
    "lidar",
    "dht11",
    "imu",
    "ultrasonic",
    "flame",
    "pir",
    "light",
    "camera",
    "pointcloud",
)
#: the kind of a typed sensor (``type = "sensor_msgs/msg/NavSatFix"``): its readings are whole
#: messages of that ROS 2 type (arpz.core.msgtypes, docs/nodes.md)
MESSAGE_KIND: Final = "message"
#: typed messages that travel as large samples (fragments on ``frames/{topic}``), as cameras do
LARGE_TYPES: frozenset[str] = frozenset(
    {"sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage", "sensor_msgs/msg/PointCloud2"}
)
#: the typed sensors ``driver = "sim"`` simulates (arpz.robot.sensors.simulated, docs/sensors.md);
#: every other type reads through a driver class
SIMULATED_TYPES: tuple[str, ...] = (
    "sensor_msgs/msg/LaserScan",
    "sensor_msgs/msg/Image",
    "sensor_msgs/msg/CompressedImage",
)
#: kinds whose readings are large (a 640x480 RGB frame is 921 600 bytes): through the reliable
#: channel they travel as fragments (``arpz.channel.FrameWriter``) on ``frames/{topic}``
LARGE_KINDS: frozenset[str] = frozenset({"camera", "pointcloud"})
#: a large reading is refused above this by the CEDDP unless its ``max_sample_bytes`` names the
#: kind
LARGE_SAMPLE_BYTES = 2 * 2**20


class SensorConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """One sensor of a robot, published on ``arpz/{fleet}/robot/{robot}/sensor/{name}``."""

    name: str
    #: one of seed 001's nine scalar kinds (SENSOR_KINDS); left out with ``type``
    kind: SensorKind = MESSAGE_KIND
    #: a ROS 2 message type ("sensor_msgs/msg/NavSatFix"): the sensor's readings are whole
    #: messages of it, from a driver class (docs/nodes.md) or, for SIMULATED_TYPES, "sim"
    type: str | None = None
    rate_hz: float = 10.0
    #: "sim" (seeded simulated driver), "replay" (plays ``trace``), or "module.path:ClassName"
    driver: str = "sim"
    trace: str | None = None
    #: floats closer than this to the last sent value count as unchanged (local cache)
    tolerance: float = 0.0
    #: a typed sensor's fields (top-level or dotted, "position.x") that count as unchanged
    #: within a band: ``cache_deadband = { latitude = 1e-6 }`` (local cache, docs/nodes.md)
    cache_deadband: dict[str, float] = msgspec.field(default_factory=dict)
    #: overrides the robot's local_cache.max_silence_s for this sensor
    max_silence_s: float | None = None
    #: the fastest this sensor can be read; a QoS assignment above it is refused
    max_rate_hz: float | None = None
    #: how much this topic matters to the per-topic QoS optimiser (``[qos] mode = "per_topic"``
    #: of the CEDDP): its share of the rate budget grows in proportion (docs/qos-optimiser.md)
    priority: float = 1.0
    seed: int | None = None
    #: a NaN or infinity from the driver: "refuse" (a driver error, counted, never a sample; in a
    #: typed message, in its scalar float fields), "refuse_all" (a typed message's arrays too:
    #: REP 117 lets a LaserScan's ranges hold them, so they pass by default) or "pass"
    nan: Literal["refuse", "refuse_all", "pass"] = "refuse"
    #: free-form options handed to the driver (e.g. a GPIO pin for a hardware driver)
    options: dict[str, Any] = msgspec.field(default_factory=dict)

    def __post_init__(self) -> None:
        keys.check_chunk(self.name, what="sensor name")
        self._check_type()
        if self.name == "hello":
            raise ValueError("'hello' is reserved for the Hello round-trip probe")
        if not self.rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {self.rate_hz}")
        if self.tolerance < 0:
            raise ValueError(f"tolerance must be >= 0, got {self.tolerance}")
        if self.cache_deadband and self.kind != MESSAGE_KIND:
            raise ValueError(
                f"sensor {self.name!r}: cache_deadband is for a typed sensor's fields; a "
                f"{self.kind} sensor has tolerance"
            )
        bad = {k: v for k, v in self.cache_deadband.items() if not (math.isfinite(v) and v >= 0)}
        if bad:
            raise ValueError(f"sensor {self.name!r}: cache_deadband must be >= 0, got {bad}")
        if self.max_silence_s is not None and self.max_silence_s <= 0:
            raise ValueError(f"max_silence_s must be > 0, got {self.max_silence_s}")
        if not (math.isfinite(self.priority) and self.priority > 0):
            raise ValueError(f"priority must be a finite number > 0, got {self.priority}")
        if self.kind == MESSAGE_KIND and self.driver == "replay":
            raise ValueError(
                f"sensor {self.name!r} of type {self.type}: a typed sensor cannot replay a trace "
                "(traces hold text values): use a driver class, driver = 'module.path:ClassName' "
                "(docs/nodes.md)"
            )
        if self.kind == MESSAGE_KIND and self.driver == "sim" and self.type not in SIMULATED_TYPES:
            raise ValueError(
                f"sensor {self.name!r} of type {self.type}: no simulated driver for this type "
                f"(driver 'sim' simulates {', '.join(SIMULATED_TYPES)}): give a driver class, "
                "driver = 'module.path:ClassName' (docs/nodes.md)"
            )
        if self.driver == "replay" and not self.trace:
            raise ValueError("driver 'replay' needs a 'trace' file (CSV or JSON lines)")
        if self.driver == "replay" and self.kind in LARGE_KINDS:
            raise ValueError(
                f"a {self.kind} sensor cannot replay a trace (traces hold text values): use "
                "driver 'sim' or a driver class (docs/sensors.md)"
            )

    def _check_type(self) -> None:
        if self.type is None:
            if self.kind == MESSAGE_KIND:
                raise ValueError(
                    f"sensor {self.name!r} needs a kind (one of {', '.join(SENSOR_KINDS)}) or a "
                    'type (a ROS 2 message type such as "sensor_msgs/msg/NavSatFix")'
                )
            return
        parts = self.type.split("/")
        if len(parts) != 3 or parts[1] != "msg" or not all(parts):
            raise ValueError(
                f"sensor {self.name!r}: type must be a ROS 2 message type package/msg/Name, such "
                f'as "sensor_msgs/msg/NavSatFix", got {self.type!r}'
            )
        if self.kind != MESSAGE_KIND:
            raise ValueError(
                f"sensor {self.name!r}: give kind (one of the nine scalar kinds) or type (a ROS 2 "
                f"message type), not both (kind {self.kind!r}, type {self.type!r})"
            )

    @property
    def large(self) -> bool:
        """Its readings travel as large samples (fragments on ``frames/{topic}``)."""
        return self.kind in LARGE_KINDS or self.type in LARGE_TYPES


class LocalCacheConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    enabled: bool = True
    #: the longest a topic may stay silent: after this an unchanged value is sent anyway, so the
    #: CEDDP can tell "unchanged" from "dead"
    max_silence_s: float = 1.0

    def __post_init__(self) -> None:
        if self.max_silence_s <= 0:
            raise ValueError(f"max_silence_s must be > 0, got {self.max_silence_s}")


class HelloConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """The Hello round-trip probe of seed 001 Fig. 9; only the origin robot enables it."""

    enabled: bool = False
    rate_hz: float = 10.0
    #: a Hello not back after this long is counted as lost
    timeout_s: float = 2.0

    def __post_init__(self) -> None:
        if not self.rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {self.rate_hz}")
        if not self.timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {self.timeout_s}")


class SimConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """Simulate this robot's body in a 2-D world (issue 6): the 8 LIDAR beams become 8 sensor
    topics ``lidar_0`` ... ``lidar_315`` and ``cmd/velocity`` drives the kinematics."""

    #: a built-in map ("hallway", "hallway_small") or a map file (TOML or JSON)
    world: str = "hallway"
    beam_rate_hz: float = 20.0
    noise_std_m: float = 0.01
    step_hz: float = 50.0
    telemetry_hz: float = 10.0

    def __post_init__(self) -> None:
        for name in ("beam_rate_hz", "step_hz", "telemetry_hz"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if self.noise_std_m < 0:
            raise ValueError(f"noise_std_m must be >= 0, got {self.noise_std_m}")


class TrafficQos(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """The reliable channel's profile of each kind of traffic (arpz/core/traffic.py explains the
    defaults). Robots and the CEDDP must agree on them; each side checks the other's offers."""

    #: "channel" (every key through the reliable channel) or "none" (plain Zenoh puts)
    reliability: ChannelMode = "channel"
    #: every sensor topic of a robot
    sensor_qos: QosProfile = SENSOR_QOS
    #: the four Hello hops; None: the sensor profile (Hello is one more topic in seed 001)
    hello_qos: QosProfile | None = None
    #: CEDDP -> robot commands (``cmd/{name}``); keep a lifespan so a late command is dropped
    command_qos: QosProfile = COMMAND_QOS
    #: the QoS assignment (``ceddp/qos``); TRANSIENT_LOCAL so a (re)joining robot gets it
    assignment_qos: QosProfile = ASSIGNMENT_QOS
    #: stats, announcements, QoS acks, telemetry and the CEDDP's stats
    report_qos: QosProfile = REPORT_QOS
    #: camera and point-cloud sensors (``frames/{topic}``): depth and max_samples count frames
    frames_qos: QosProfile = FRAMES_QOS
    #: for benchmarks only (benchmarks/downlink_hello.py): the CEDDP -> robot keys as plain puts,
    #: arpz's downlink before issue 14; set on both sides
    plain_downlink: bool = False

    @property
    def channel(self) -> bool:
        return self.reliability == "channel"

    def profile(self, kind: str, *, downlink: bool = False) -> QosProfile | None:
        """The profile of ``kind`` ("sensor", "hello", "command", "assignment", "report",
        "frames"), or
        None in plain mode (``downlink``: for a CEDDP -> robot key)."""
        if not self.channel or (downlink and self.plain_downlink):
            return None
        if kind == "hello":
            return self.hello_qos or self.sensor_qos
        profile: QosProfile = getattr(self, f"{kind}_qos")
        return profile


class WatchdogConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """Stop the actuators when a command topic goes silent past its deadline (the CEDDP died or
    the link is down); the robot resumes on the next command (docs/sensors.md)."""

    enabled: bool = True
    #: command name -> deadline (s); None: ``velocity`` 0.5 s for a simulated body, else nothing
    deadlines_s: dict[str, float] | None = None

    def __post_init__(self) -> None:
        for name, deadline in (self.deadlines_s or {}).items():
            keys.check_chunk(name, what="watchdog command name")
            if not deadline > 0:
                raise ValueError(f"deadlines_s.{name} must be > 0 seconds, got {deadline}")


class RobotClockConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """The robot's clock against the CEDDP's (``[clock]`` of a robot; docs/operations.md): a
    burst of NTP-style exchanges every ``period_s``, the fastest of the last ``window`` kept."""

    enabled: bool = True
    period_s: float = 2.0
    #: exchanges per period (the fastest of them is the least disturbed by queues)
    burst: int = 4
    #: exchanges the estimate is chosen from (the last ones)
    window: int = 16
    #: a request not answered within this is given up
    timeout_s: float = 1.0
    #: TEST AND DIAGNOSTIC AID: add this many seconds to every stamp the robot makes (sensor
    #: samples, reports, clock requests), as if its clock were that far off; 0 on a real robot
    shift_s: float = 0.0

    def __post_init__(self) -> None:
        for name in ("period_s", "timeout_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0 seconds, got {getattr(self, name)}")
        for name in ("burst", "window"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")


class LinkConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """How a robot notices its link to the CEDDP died and gets it back (``[link]`` of a robot;
    ``arpz.robot.link_monitor``; docs/operations.md, "Drops and reconnection"). The defaults
    were chosen in the namespace lab of issue 39 (docs/deploy.md, "Link timing")."""

    #: watch the link and reopen the session when it died (false: Zenoh's own reconnection
    #: only, which over TLS may take 15 minutes after a roam)
    reopen: bool = True
    #: nothing heard from the CEDDP (acknowledgements, clock replies, commands, its presence)
    #: this long while something sent waits for it: the link is lost
    silence_s: float = 3.0
    #: after silence or the CEDDP's presence vanishing, how long Zenoh's own session gets to
    #: come back before the robot reopens it (after a change of address: no wait)
    zenoh_grace_s: float = 1.0
    #: from the start of one reopen attempt that failed at once (refused, no route) to the
    #: next: doubles from the first figure to the second (one that waited for the link, at
    #: least the first figure, is followed at once: it was the wait)
    reopen_backoff_s: float = 0.25
    reopen_backoff_max_s: float = 1.0
    #: how often the link is checked
    check_period_s: float = 0.1
    #: a change of the robot's source address towards the CEDDP (a roam) is a lost link at once
    #: (never for ``quic/`` endpoints alone: QUIC moves its connection to the new address)
    watch_address: bool = True

    def __post_init__(self) -> None:
        for name in (
            "silence_s",
            "reopen_backoff_s",
            "reopen_backoff_max_s",
            "check_period_s",
        ):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0 seconds, got {getattr(self, name)}")
        if self.zenoh_grace_s < 0:
            raise ValueError(f"zenoh_grace_s must be >= 0 seconds, got {self.zenoh_grace_s}")
        if self.reopen_backoff_max_s < self.reopen_backoff_s:
            raise ValueError(
                f"reopen_backoff_max_s ({self.reopen_backoff_max_s}) must be >= "
                f"reopen_backoff_s ({self.reopen_backoff_s})"
            )


class PluginConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """A team's class named in a config: ``class = "mylab.dock:DockPlanner"`` and the
    ``options`` table it is made with (docs/nodes.md)."""

    cls: str = msgspec.field(name="class")
    options: dict[str, Any] = msgspec.field(default_factory=dict)

    def __post_init__(self) -> None:
        module, sep, name = self.cls.partition(":")
        if not (module and sep and name):
            raise ValueError(f"class must be 'module.path:ClassName', got {self.cls!r}")


class ServiceConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """One service a robot serves on ``arpz/{fleet}/robot/{robot}/srv/{name}`` (docs/nodes.md
    "Services"): ``[[services]] name = "dock"  type = "std_srvs/srv/Trigger"  handler =
    "mylab.base:dock"``."""

    name: str
    #: a ROS 2 service type, package/srv/Name ("std_srvs/srv/Trigger")
    type: str
    #: "module.path:function" (called with the request, returns the response) or
    #: "module.path:Class" (made once with ``options``, then called with each request)
    handler: str
    #: requests waiting for the handler at most; one more is refused at once as busy
    queue: int = 8
    #: free-form options handed to a handler class
    options: dict[str, Any] = msgspec.field(default_factory=dict)

    def __post_init__(self) -> None:
        keys.check_chunk(self.name, what="service name")
        parts = self.type.split("/")
        if len(parts) != 3 or parts[1] != "srv" or not all(parts):
            raise ValueError(
                f"service {self.name!r}: type must be a ROS 2 service type package/srv/Name, such "
                f'as "std_srvs/srv/Trigger", got {self.type!r}'
            )
        module, sep, attr = self.handler.partition(":")
        if not (module and sep and attr):
            raise ValueError(
                f"service {self.name!r}: handler must be 'module.path:function' or "
                f"'module.path:Class', got {self.handler!r}"
            )
        if not 1 <= self.queue <= 10_000:
            raise ValueError(f"service {self.name!r}: queue must be 1 .. 10000, got {self.queue}")


class RobotConfig(TrafficQos, forbid_unknown_fields=True, frozen=True, kw_only=True):
    robot_id: str
    fleet: str = "default"
    #: the server's endpoints; empty: those of ``zenoh_config``, or DEFAULT_CONNECT without one
    connect: list[str] = msgspec.field(default_factory=list)
    #: a Zenoh JSON5 config file (TLS, access control...) applied before the fields above
    zenoh_config: str | None = None
    #: "machine1", "machine2", "machine3" (seed 001's sensor sets) or None
    preset: str | None = None
    #: publish rate of the preset's sensors
    preset_rate_hz: float = 10.0
    sensors: list[SensorConfig] = msgspec.field(default_factory=list)
    #: folders of a team's ``.msg`` files (``PACKAGE/msg/NAME.msg``, as ROS 2 lays them out),
    #: relative to the config's folder; the CEDDP needs the same (docs/nodes.md)
    msg_paths: list[str] = msgspec.field(default_factory=list)
    local_cache: LocalCacheConfig = msgspec.field(default_factory=LocalCacheConfig)
    hello: HelloConfig = msgspec.field(default_factory=HelloConfig)
    #: simulate the body in a 2-D world (None: a real robot, or sensors only)
    sim: SimConfig | None = None
    #: the team's actuator (``[actuator] class = "mylab.base:Base"``, docs/nodes.md); None: a
    #: robot that only senses (or the simulated body's, with ``sim``)
    actuator: PluginConfig | None = None
    #: the services this robot serves (``[[services]]``, docs/nodes.md "Services")
    services: list[ServiceConfig] = msgspec.field(default_factory=list)
    watchdog: WatchdogConfig = msgspec.field(default_factory=WatchdogConfig)
    clock: RobotClockConfig = msgspec.field(default_factory=RobotClockConfig)
    link: LinkConfig = msgspec.field(default_factory=LinkConfig)
    seed: int = 0
    stats_period_s: float = 0.5
    announce_period_s: float = 2.0
    #: payload bytes per fragment of a camera frame or point cloud; None: by the link, 60 KiB
    #: when every ``connect`` endpoint is a stream (tcp, tls, quic...), else 1280 (one radio
    #: frame: a lost UDP datagram costs one fragment); docs/reliability.md "Large samples"
    frame_fragment_bytes: int | None = None
    #: the sensor messages of one scheduler tick leave as one Zenoh message (a bundle,
    #: docs/protocol.md "Bundles"): at 100 Hz a CEDDP spends most of its CPU per message, not per
    #: byte. Off by default for now: an overloaded CEDDP fed bundles did not bring its latency
    #: back within its bound after cutting the budget (tests/integration/test_overload.py fails
    #: with it on), which is not understood yet
    bundle_sensors: bool = False
    #: how long to keep trying to reach the server at start-up
    connect_timeout_s: float = 30.0
    #: how long to wait at start-up for the CEDDP's readers to match each topic
    match_timeout_s: float = 5.0
    #: 0 = run until SIGINT/SIGTERM
    duration_s: float = 0.0

    def __post_init__(self) -> None:
        keys.check_chunk(self.robot_id, what="robot_id")
        keys.check_chunk(self.fleet, what="fleet")
        check_endpoints(self.connect, field="connect")
        if self.preset is not None and self.preset not in ("machine1", "machine2", "machine3"):
            raise ValueError(f"preset must be machine1, machine2 or machine3, got {self.preset!r}")
        if not self.preset_rate_hz > 0:
            raise ValueError(f"preset_rate_hz must be > 0, got {self.preset_rate_hz}")
        names = [s.name for s in self.sensors]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"sensor names must be unique, repeated: {', '.join(dupes)}")
        services = [s.name for s in self.services]
        repeated = sorted({n for n in services if services.count(n) > 1})
        if repeated:
            raise ValueError(f"service names must be unique, repeated: {', '.join(repeated)}")
        if self.stats_period_s <= 0 or self.announce_period_s <= 0:
            raise ValueError("stats_period_s and announce_period_s must be > 0")
        if self.frame_fragment_bytes is not None and not (
            256 <= self.frame_fragment_bytes <= MAX_FRAGMENT_BYTES
        ):
            raise ValueError(
                f"frame_fragment_bytes must be 256 .. {MAX_FRAGMENT_BYTES} (a fragment must fit "
                f"one Zenoh batch), got {self.frame_fragment_bytes}"
            )
        if self.duration_s < 0:
            raise ValueError("duration_s must be >= 0 (0 = run until stopped)")
        if self.sim is not None and self.actuator is not None:
            raise ValueError(
                "actuator and sim both drive the robot: the simulated body has its own actuator; "
                "give one of them"
            )


class CeddpHelloConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """Where the CEDDP sends a Hello from the origin (seed 001 Fig. 9: robot 1 via robot 3)."""

    relay: str | None = None

    def __post_init__(self) -> None:
        if self.relay is not None:
            keys.check_chunk(self.relay, what="hello.relay")


class QosLimitsConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """Per-robot limits of the QoS optimiser (any field left out uses the [qos] default)."""

    rmax_hz: float | None = None
    rmin_hz: float | None = None
    dmax: int | None = None
    dmin: int | None = None


class QosControlConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """Live QoS balancing (seed 001 section 2.4): R and D for every robot, re-solved when the
    fleet changes."""

    enabled: bool = False
    rmax_hz: float = 100.0
    rmin_hz: float = 1.0
    dmax: int = 5000
    dmin: int = 1
    #: "paper" (eq. 5), "loss_aware" or "max" (the larger): see docs/qos-optimiser.md
    depth_policy: Literal["paper", "loss_aware", "max"] = "paper"
    #: the link model for the loss-aware depth (used by "loss_aware" and "max")
    link_rtt_ms: float = 5.0
    link_loss_pct: float = 0.0
    robots: dict[str, QosLimitsConfig] = msgspec.field(default_factory=dict)
    #: the offered deadline the robots are told, in periods of their assigned rate: seed 001's
    #: 1/R is 1.0, which scheduling jitter misses on most ticks; 1.5 tolerates half a period
    deadline_periods: float = 1.5
    #: "fleet": seed 001's one R and D for every topic; "per_topic": a rate and a depth for each
    #: topic by its priority and measured change rate, with the link quality measured from the
    #: reliable channel's counters and re-solved when it changes (docs/qos-optimiser.md)
    mode: Literal["fleet", "per_topic"] = "fleet"
    #: per_topic: a measured input (loss, round trip, burst, change rate) must move by this
    #: share of its value in force (and loss by at least ``loss_step_pct`` points) in two
    #: measurements in a row before the problem is re-solved
    hysteresis: float = 0.5
    loss_step_pct: float = 1.0
    #: per_topic: sensor samples a robot must have sent before its link is measured again
    measure_samples: int = 200
    #: per_topic: the shortest time between two re-solves caused by measurements
    min_resolve_interval_s: float = 2.0
    #: closed loop: on a link measured to lose at least ``heartbeat_loss_pct`` % of its
    #: transmissions, the robot's sensor writers are told a heartbeat period of
    #: ``heartbeat_rtts`` measured round trips (at least ``heartbeat_min_ms``, at most the
    #: [sensor_qos] period): a lost last sample waits for a heartbeat, so the period is the p99
    #: of recovery on a lossy link. 0 rtts: never assigned (docs/qos-optimiser.md)
    heartbeat_rtts: float = 2.0
    heartbeat_min_ms: float = 20.0
    heartbeat_loss_pct: float = 0.2

    def __post_init__(self) -> None:
        if not (
            self.heartbeat_rtts >= 0 and self.heartbeat_min_ms > 0 and self.heartbeat_loss_pct >= 0
        ):
            raise ValueError(
                "need heartbeat_rtts >= 0 (0: never assign a heartbeat), heartbeat_min_ms > 0 "
                f"and heartbeat_loss_pct >= 0, got {self.heartbeat_rtts}, "
                f"{self.heartbeat_min_ms} and {self.heartbeat_loss_pct}"
            )
        if not self.deadline_periods >= 1:
            raise ValueError(
                f"deadline_periods must be >= 1 (1 is seed 001's 1/R), got {self.deadline_periods}"
            )
        if not 0 < self.rmin_hz <= self.rmax_hz:
            raise ValueError(f"need 0 < rmin_hz <= rmax_hz, got {self.rmin_hz} and {self.rmax_hz}")
        if not 1 <= self.dmin <= self.dmax:
            raise ValueError(f"need 1 <= dmin <= dmax, got {self.dmin} and {self.dmax}")
        if not (self.hysteresis > 0 and self.loss_step_pct >= 0):
            raise ValueError("hysteresis must be > 0 and loss_step_pct >= 0")
        if self.measure_samples < 1 or self.min_resolve_interval_s < 0:
            raise ValueError("measure_samples must be >= 1 and min_resolve_interval_s >= 0")


class OverloadConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """Graceful overload (arpz/ceddp/overload.py, docs/operations.md): the CEDDP measures its
    capacity and, when it cannot keep up, makes it the fleet's rate budget through [qos]."""

    enabled: bool = True
    #: share of an interval the sensor path's thread works (does not wait for samples) from
    #: which the CEDDP counts as saturated
    busy_bound: float = 0.9
    #: p99 latency (robot stamp to ingest) the fleet must stay within
    latency_bound_ms: float = 100.0
    #: overloaded metrics intervals in a row before the budget is cut
    trigger_intervals: int = 2
    #: the budget is this share of the measured capacity
    headroom: float = 0.8
    #: intervals to wait after a change (the backlog drains) before judging again
    hold_intervals: int = 6
    #: calm intervals in a row before the budget grows again, and by how much
    recover_intervals: int = 10
    recover_step: float = 1.25
    #: a stand-in for a heavier planner: every reading the planners see costs this much CPU
    #: time (capacity drills and the overload test; 0 = off)
    planner_cost_us: float = 0.0

    def __post_init__(self) -> None:
        if not 0 < self.busy_bound <= 1:
            raise ValueError(f"busy_bound must be in (0, 1], got {self.busy_bound}")
        if not 0 < self.headroom <= 1:
            raise ValueError(f"headroom must be in (0, 1], got {self.headroom}")
        if self.latency_bound_ms <= 0:
            raise ValueError(f"latency_bound_ms must be > 0, got {self.latency_bound_ms}")
        if self.recover_step <= 1:
            raise ValueError(f"recover_step must be > 1, got {self.recover_step}")
        if self.planner_cost_us < 0:
            raise ValueError(f"planner_cost_us must be >= 0, got {self.planner_cost_us}")
        for name in ("trigger_intervals", "hold_intervals", "recover_intervals"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")


class MissionConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """Run the hallway mission of seed 001 section 3.2 on this CEDDP (issue 6)."""

    kind: Literal["hallway"] = "hallway"
    #: the same world the robots simulate: "hallway", "hallway_small" or a map file
    world: str = "hallway"
    time_limit_s: float = 150.0
    #: how often the planner decides and sends velocity commands
    tick_hz: float = 20.0
    #: LIDAR data older than this stops the fleet (about 3 periods of the nominal beam rate)
    max_age_s: float = 0.3

    def __post_init__(self) -> None:
        for name in ("time_limit_s", "tick_hz", "max_age_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")


class CeddpClockConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """The CEDDP's side of clock offsets (``[clock]`` of the CEDDP; docs/operations.md): answer
    the robots' clock requests, correct latencies by each robot's offset, flag a robot whose
    |offset| exceeds ``max_offset_ms``."""

    #: answer clock requests on ``ceddp/clock`` (off: robots get no estimate, nothing corrected)
    serve: bool = True
    #: correct latency and staleness by each robot's reported offset
    correct: bool = True
    max_offset_ms: float = 50.0

    def __post_init__(self) -> None:
        if not self.max_offset_ms > 0:
            raise ValueError(f"max_offset_ms must be > 0, got {self.max_offset_ms}")


#: the ROS 2 message types a ``[[ros2.commands]]`` mapping may name: each converts to an arpz
#: command value (arpz/bridge/commands.py; Twist -> [linear.x, angular.z], the simulated body's
#: ``velocity``)
ROS2_COMMAND_TYPES: tuple[str, ...] = (
    "geometry_msgs/msg/Twist",
    "std_msgs/msg/Float64",
    "std_msgs/msg/Bool",
    "std_msgs/msg/String",
)
_ROS2_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def _check_ros2_template(template: str, *, what: str) -> None:
    """A ROS 2 topic name template: absolute, ``{robot}`` / ``{topic}`` placeholders only."""
    probe = template.replace("{robot}", "r").replace("{topic}", "t")
    tokens = probe.split("/")
    if not template.startswith("/") or any(not _ROS2_NAME.match(t) for t in tokens[1:]):
        raise ValueError(
            f"{what} {template!r} is not an absolute ROS 2 topic name: write '/' then names of "
            "letters, digits and '_' separated by '/', with {robot} and {topic} as placeholders "
            "(e.g. '/{robot}/scan')"
        )


class Ros2CommandConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """One ROS 2 topic per robot whose messages become arpz commands to that robot
    (docs/ros2.md "Commands")."""

    #: the ROS 2 topic, ``{robot}`` replaced by each robot's id
    topic: str = "/{robot}/cmd_vel"
    type: str = "geometry_msgs/msg/Twist"
    #: the arpz command (``cmd/{command}``) the robot must act on (its announcement lists it)
    command: str = "velocity"

    def __post_init__(self) -> None:
        _check_ros2_template(self.topic, what="ros2.commands topic")
        if "{robot}" not in self.topic:
            raise ValueError(
                f"ros2.commands topic {self.topic!r} must contain {{robot}}: each robot gets "
                "its own command topic"
            )
        parts = self.type.split("/")
        if len(parts) != 3 or parts[1] != "msg" or not all(parts):
            raise ValueError(
                f"ros2.commands type {self.type!r} is not a ROS 2 message type package/msg/Name: "
                f"use one of {', '.join(ROS2_COMMAND_TYPES)} (converted to a value), or the type "
                "a robot's actuator takes (command_types; passed through as the message)"
            )
        keys.check_chunk(self.command, what="ros2.commands command")


class Ros2Config(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """The ROS 2 bridge (``[ros2]``, docs/ros2.md): the fleet's topics as ROS 2 topics, ROS 2
    commands and service calls to the robots."""

    enabled: bool = False
    #: how the bridge reaches ROS 2: "rmw_zenoh" speaks rmw_zenoh's protocol on the fleet's own
    #: router (no ROS 2 installed); "rclpy" is a real ROS 2 node on whatever RMW the host's
    #: ROS 2 uses (Fast DDS by default, ``RMW_IMPLEMENTATION``), needing ``arpz[ros2]``
    backend: Literal["rmw_zenoh", "rclpy"] = "rmw_zenoh"
    #: ROS_DOMAIN_ID of the ROS 2 side (rmw_zenoh's first key chunk; the rclpy node's domain)
    domain_id: int = 0
    #: the one ROS 2 node the bridge appears as (``ros2 node list``)
    node_name: str = "arpz_bridge"
    #: arpz topic -> ROS 2 topic name: keys "robot/topic" or "*/topic" (any robot), values
    #: absolute names with ``{robot}`` and ``{topic}`` placeholders; unnamed topics follow the
    #: default table of docs/ros2.md (``/{robot}/scan`` for the LIDAR, ...)
    topics: dict[str, str] = msgspec.field(default_factory=dict)
    commands: list[Ros2CommandConfig] = msgspec.field(default_factory=lambda: [Ros2CommandConfig()])
    #: samples and commands waiting for the bridge's worker; beyond it the readers wait
    queue_limit: int = 10_000

    def __post_init__(self) -> None:
        if not 0 <= self.domain_id <= 232:
            raise ValueError(f"ros2.domain_id must be 0..232 (ROS_DOMAIN_ID), got {self.domain_id}")
        if not _ROS2_NAME.match(self.node_name):
            raise ValueError(
                f"ros2.node_name {self.node_name!r} is not a ROS 2 node name: letters, digits "
                "and '_', not starting with a digit"
            )
        for pattern, template in self.topics.items():
            robot, _, topic = pattern.partition("/")
            if not topic or (robot != "*" and not _ROS2_KEY.match(robot)):
                raise ValueError(f"ros2.topics key {pattern!r} must be 'robot/topic' or '*/topic'")
            keys.check_chunk(topic, what="ros2.topics topic")
            _check_ros2_template(template, what=f"ros2.topics.{pattern!r}")
        if self.queue_limit < 1:
            raise ValueError(f"ros2.queue_limit must be >= 1, got {self.queue_limit}")


_ROS2_KEY = re.compile(r"^[a-z0-9][a-z0-9_\-]*$")


class CeddpConfig(TrafficQos, forbid_unknown_fields=True, frozen=True, kw_only=True):
    fleet: str = "default"
    #: where robots connect; empty: the endpoints of ``zenoh_config``, or DEFAULT_LISTEN without
    listen: list[str] = msgspec.field(default_factory=list)
    #: with TLS in ``zenoh_config``, a plain ``tcp/`` listen endpoint is refused unless this is set
    allow_plain_tcp: bool = False
    #: other CEDDP routers to join in one Zenoh router mesh (scale-out, docs/deploy.md)
    connect: list[str] = msgspec.field(default_factory=list)
    #: the robots this CEDDP ingests and plans for: "*", an id, or a pattern such as "east-$*";
    #: reports, presence and QoS stay fleet-wide
    partition: str = "*"
    zenoh_config: str | None = None
    #: the Rerun recording written always; the parent folder is created
    rrd: str = "ceddp.rrd"
    #: serve a live gRPC sink for a Rerun viewer on this port (0 = off)
    grpc_port: int = 0
    #: serve the Rerun web viewer on this port, connected to ``grpc_port`` (0 = off;
    #: docs/tools.md "Live views"); the status page links to it
    rerun_web_port: int = 0
    #: serve the fleet status page, ``/api/status`` and Prometheus ``/metrics`` on this port
    #: (0 = off; docs/tools.md "Live views")
    web_port: int = 0
    #: serve a Foxglove WebSocket server (live sensor topics and metrics) on this port (0 = off)
    foxglove_port: int = 0
    #: the address ``web_port`` and ``foxglove_port`` bind ("0.0.0.0": every interface)
    live_host: str = "127.0.0.1"
    #: a JSON summary written at shutdown (None = not written), and every summary_period_s
    #: while running ("complete": false), so that a killed CEDDP leaves one to reconcile against
    summary_json: str | None = None
    summary_period_s: float = 5.0
    #: the summary of the previous run (a path, or "latest": the newest summary*.json beside
    #: summary_json at start): samples it had already received are flagged when a restart's
    #: TRANSIENT_LOCAL catch-up delivers them again (``repeated_from_previous_run``)
    previous_summary: str | None = None
    cache_control: bool = True
    metrics_period_s: float = 0.5
    #: samples waiting for the ingest worker; beyond this Zenoh applies backpressure to robots
    ingest_queue_limit: int = 100_000
    #: bounds on per-topic state: samples from more robots or topics are dropped and counted
    max_robots: int = 1000
    max_topics_per_robot: int = 64
    #: reports and events waiting for the control worker (the latest per key; docs/operations.md)
    control_queue_limit: int = 4096
    #: a report (stats, announce, telemetry, QoS ack) larger than this is refused undecoded
    max_report_bytes: int = 262_144
    #: a sensor sample larger than this is refused undecoded, by the kind the robot announced
    #: for its topic; "default" for other kinds and topics not yet announced
    max_sample_bytes: dict[str, int] = msgspec.field(default_factory=lambda: {"default": 65_536})
    hello: CeddpHelloConfig = msgspec.field(default_factory=CeddpHelloConfig)
    qos: QosControlConfig = msgspec.field(default_factory=QosControlConfig)
    overload: OverloadConfig = msgspec.field(default_factory=OverloadConfig)
    mission: MissionConfig | None = None
    clock: CeddpClockConfig = msgspec.field(default_factory=CeddpClockConfig)
    #: the ROS 2 bridge (docs/ros2.md); off unless ``enabled``
    ros2: Ros2Config = msgspec.field(default_factory=Ros2Config)
    #: a team's planners (``[[planners]]``, docs/nodes.md), beside the built-in ones
    planners: list[PluginConfig] = msgspec.field(default_factory=list)
    #: folders of a team's ``.msg`` files, as the robots' (docs/nodes.md)
    msg_paths: list[str] = msgspec.field(default_factory=list)
    #: 0 = run until SIGINT/SIGTERM
    duration_s: float = 0.0

    def __post_init__(self) -> None:
        keys.check_chunk(self.fleet, what="fleet")
        keys.check_partition(self.partition)
        check_endpoints(self.listen, field="listen")
        check_endpoints(self.connect, field="connect")
        if not 0 <= self.grpc_port <= 65535:
            raise ValueError(f"grpc_port must be 0..65535, got {self.grpc_port}")
        self._check_live_ports()
        if self.metrics_period_s <= 0:
            raise ValueError("metrics_period_s must be > 0")
        if self.summary_period_s < 0:
            raise ValueError("summary_period_s must be >= 0 (0: only at shutdown)")
        if any(n < 1 for n in self.max_sample_bytes.values()):
            raise ValueError(f"max_sample_bytes must all be >= 1, got {self.max_sample_bytes}")
        for name in ("ingest_queue_limit", "control_queue_limit", "max_report_bytes"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")

    def _check_live_ports(self) -> None:
        """The live views' ports (docs/tools.md "Live views"): each 0..65535, no two the same,
        and the Rerun web viewer only with the gRPC server it shows."""
        ports = {
            name: getattr(self, name)
            for name in ("grpc_port", "rerun_web_port", "web_port", "foxglove_port")
        }
        for name, port in ports.items():
            if not 0 <= port <= 65535:
                raise ValueError(f"{name} must be 0..65535 (0 = off), got {port}")
        used: dict[int, str] = {}
        for name, port in ports.items():
            if port and port in used:
                raise ValueError(f"{name} and {used[port]} are both {port}: give each its own port")
            used.setdefault(port, name)
        if self.rerun_web_port and not self.grpc_port:
            raise ValueError(
                "rerun_web_port needs grpc_port: the web viewer shows the live recording the "
                "gRPC server serves; set grpc_port too"
            )
        if not self.live_host:
            raise ValueError('live_host must be an address to bind, such as "127.0.0.1"')


class BridgeConfig(TrafficQos, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """``python -m arpz.bridge --config FILE``: the ROS 2 bridge on a machine of its own, a
    client of the fleet's router. The traffic profiles must be the fleet's (as a robot's)."""

    fleet: str = "default"
    #: the fleet's router; empty: the ``--connect`` flag or the local default
    connect: list[str] = msgspec.field(default_factory=list)
    zenoh_config: str | None = None
    ros2: Ros2Config = msgspec.field(default_factory=lambda: Ros2Config(enabled=True))
    #: folders of the fleet's own ``.msg`` files, as the robots' (relative to the config's)
    msg_paths: list[str] = msgspec.field(default_factory=list)

    def __post_init__(self) -> None:
        keys.check_chunk(self.fleet, what="fleet")
        check_endpoints(self.connect, field="connect")


T = TypeVar("T", bound=msgspec.Struct)


def load_toml(path: str | Path, kind: type[T], overrides: dict[str, Any] | None = None) -> T:
    """Read ``path`` as TOML into ``kind``; ``overrides`` (from command-line flags) win.

    Raises ConfigError with the file name, the field path and the reason.
    """
    path = Path(path)
    try:
        raw = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise ConfigError(f"{path}: file not found") from None
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    return from_dict(raw, kind, overrides, source=str(path))


def from_dict(
    raw: dict[str, Any], kind: type[T], overrides: dict[str, Any] | None = None, *, source: str
) -> T:
    data = dict(raw)
    for key, value in (overrides or {}).items():
        if value is not None:
            data[key] = value
    try:
        return msgspec.convert(data, kind)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"{source}: {_explain(exc)}") from None


#: the two meanings of "reliability" (the demo's one flag covers both): the fleet's mode at the
#: top of the file, and a QoS profile's policy inside a ``[*_qos]`` table
_RELIABILITY_HINTS = {
    "mode": (
        ' (the top-level reliability is the fleet\'s mode: "channel" or "none"; '
        'best effort is a QoS policy: reliability = "best_effort" in [sensor_qos])'
    ),
    "policy": (
        ' (a QoS profile\'s reliability is "reliable" or "best_effort"; plain Zenoh '
        'without the channel is the fleet\'s mode: reliability = "none" at the top of the '
        "file, on robots and CEDDP alike)"
    ),
}


def _explain(exc: msgspec.ValidationError) -> str:
    """Turn msgspec's '... - at `$.sensors[0].rate_hz`' into 'field sensors[0].rate_hz: ...'."""
    text = str(exc)
    if " - at `$" in text:
        message, _, where = text.rpartition(" - at `$")
        field = where.rstrip("`").lstrip(".")
        hint = ""
        if field == "reliability":
            hint = _RELIABILITY_HINTS["mode"]
        elif field.endswith("_qos.reliability"):
            hint = _RELIABILITY_HINTS["policy"]
        return f"field '{field}': {message}{hint}"
    return text
