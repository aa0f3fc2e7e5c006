"""Configuration of robots and of the CEDDP: msgspec Structs loaded from TOML.

Unknown fields are errors (a typo in a TOML file must not be silently ignored), and every error
names the file, the field and what is wrong, so ``python -m arpz.robot`` can exit with code 2 and
a message the user can act on.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any, Literal, TypeVar

import msgspec

from arpz import keys
from arpz.reliability import QosProfile

SensorKind = Literal["lidar", "dht11", "imu", "ultrasonic", "flame", "pir", "light"]
SENSOR_KINDS: tuple[str, ...] = ("lidar", "dht11", "imu", "ultrasonic", "flame", "pir", "light")


class ConfigError(ValueError):
    """A configuration that cannot be used; ``str()`` names the file, the field and the problem."""


class SensorConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    """One sensor of a robot, published on ``arpz/{fleet}/robot/{robot}/sensor/{name}``."""

    name: str
    kind: SensorKind
    rate_hz: float = 10.0
    #: "sim" (seeded simulated driver), "replay" (plays ``trace``), or "module.path:ClassName"
    driver: str = "sim"
    trace: str | None = None
    #: floats closer than this to the last sent value count as unchanged (local cache)
    tolerance: float = 0.0
    #: overrides the robot's local_cache.max_silence_s for this sensor
    max_silence_s: float | None = None
    #: the fastest this sensor can be read; a QoS assignment above it is refused
    max_rate_hz: float | None = None
    seed: int | None = None
    #: free-form options handed to the driver (e.g. a GPIO pin for a hardware driver)
    options: dict[str, Any] = msgspec.field(default_factory=dict)

    def __post_init__(self) -> None:
        keys.check_chunk(self.name, what="sensor name")
        if self.name == "hello":
            raise ValueError("'hello' is reserved for the Hello round-trip probe")
        if not self.rate_hz > 0:
            raise ValueError(f"rate_hz must be > 0, got {self.rate_hz}")
        if self.tolerance < 0:
            raise ValueError(f"tolerance must be >= 0, got {self.tolerance}")
        if self.max_silence_s is not None and self.max_silence_s <= 0:
            raise ValueError(f"max_silence_s must be > 0, got {self.max_silence_s}")
        if self.driver == "replay" and not self.trace:
            raise ValueError("driver 'replay' needs a 'trace' file (CSV or JSON lines)")


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


class RobotConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    robot_id: str
    fleet: str = "default"
    connect: list[str] = msgspec.field(default_factory=lambda: ["tcp/127.0.0.1:7447"])
    #: a Zenoh JSON5 config file (TLS, access control...) applied before the fields above
    zenoh_config: str | None = None
    #: "machine1", "machine2", "machine3" (seed 001's sensor sets) or None
    preset: str | None = None
    #: publish rate of the preset's sensors
    preset_rate_hz: float = 10.0
    sensors: list[SensorConfig] = msgspec.field(default_factory=list)
    local_cache: LocalCacheConfig = msgspec.field(default_factory=LocalCacheConfig)
    hello: HelloConfig = msgspec.field(default_factory=HelloConfig)
    #: simulate the body in a 2-D world (None: a real robot, or sensors only)
    sim: SimConfig | None = None
    #: the reliable channel's QoS for every sensor topic (arpz.reliability.QosProfile fields);
    #: None: plain Zenoh puts, no end-to-end recovery
    sensor_qos: QosProfile | None = None
    seed: int = 0
    stats_period_s: float = 0.5
    announce_period_s: float = 2.0
    #: how long to keep trying to reach the server at start-up
    connect_timeout_s: float = 30.0
    #: with sensor_qos: how long to wait at start-up for the CEDDP's reader to match each topic
    match_timeout_s: float = 5.0
    #: 0 = run until SIGINT/SIGTERM
    duration_s: float = 0.0

    def __post_init__(self) -> None:
        keys.check_chunk(self.robot_id, what="robot_id")
        keys.check_chunk(self.fleet, what="fleet")
        if not self.connect:
            raise ValueError(
                "connect must list at least one endpoint, e.g. 'tcp/192.168.1.10:7447'"
            )
        if self.preset is not None and self.preset not in ("machine1", "machine2", "machine3"):
            raise ValueError(f"preset must be machine1, machine2 or machine3, got {self.preset!r}")
        if not self.preset_rate_hz > 0:
            raise ValueError(f"preset_rate_hz must be > 0, got {self.preset_rate_hz}")
        names = [s.name for s in self.sensors]
        dupes = sorted({n for n in names if names.count(n) > 1})
        if dupes:
            raise ValueError(f"sensor names must be unique, repeated: {', '.join(dupes)}")
        if self.stats_period_s <= 0 or self.announce_period_s <= 0:
            raise ValueError("stats_period_s and announce_period_s must be > 0")
        if self.duration_s < 0:
            raise ValueError("duration_s must be >= 0 (0 = run until stopped)")


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

    def __post_init__(self) -> None:
        if not 0 < self.rmin_hz <= self.rmax_hz:
            raise ValueError(f"need 0 < rmin_hz <= rmax_hz, got {self.rmin_hz} and {self.rmax_hz}")
        if not 1 <= self.dmin <= self.dmax:
            raise ValueError(f"need 1 <= dmin <= dmax, got {self.dmin} and {self.dmax}")


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


class CeddpConfig(msgspec.Struct, forbid_unknown_fields=True, frozen=True, kw_only=True):
    fleet: str = "default"
    listen: list[str] = msgspec.field(default_factory=lambda: ["tcp/0.0.0.0:7447"])
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
    #: a JSON summary written at shutdown (None = not written)
    summary_json: str | None = None
    cache_control: bool = True
    metrics_period_s: float = 0.5
    #: samples waiting for the ingest worker; beyond this Zenoh applies backpressure to robots
    ingest_queue_limit: int = 100_000
    #: bounds on per-topic state: samples from more robots or topics are dropped and counted
    max_robots: int = 1000
    max_topics_per_robot: int = 64
    hello: CeddpHelloConfig = msgspec.field(default_factory=CeddpHelloConfig)
    qos: QosControlConfig = msgspec.field(default_factory=QosControlConfig)
    mission: MissionConfig | None = None
    #: receive sensor topics through the reliable channel with this QoS (it must match what the
    #: robots offer, docs/reliability.md); None: plain Zenoh subscription
    sensor_qos: QosProfile | None = None
    #: 0 = run until SIGINT/SIGTERM
    duration_s: float = 0.0

    def __post_init__(self) -> None:
        keys.check_chunk(self.fleet, what="fleet")
        keys.check_partition(self.partition)
        if not self.listen:
            raise ValueError("listen must list at least one endpoint, e.g. 'tcp/0.0.0.0:7447'")
        if not 0 <= self.grpc_port <= 65535:
            raise ValueError(f"grpc_port must be 0..65535, got {self.grpc_port}")
        if self.metrics_period_s <= 0:
            raise ValueError("metrics_period_s must be > 0")
        if self.ingest_queue_limit < 1:
            raise ValueError("ingest_queue_limit must be >= 1")


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


def _explain(exc: msgspec.ValidationError) -> str:
    """Turn msgspec's '... - at `$.sensors[0].rate_hz`' into 'field sensors[0].rate_hz: ...'."""
    text = str(exc)
    if " - at `$" in text:
        message, _, where = text.rpartition(" - at `$")
        field = where.rstrip("`").lstrip(".")
        return f"field '{field}': {message}"
    return text
