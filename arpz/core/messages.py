"""Wire types of arpz: every payload on every arpz key, as msgspec Structs encoded with msgpack.

Data-carrying messages (``Sample``, ``Hello``, ``Command``) are ``array_like`` so that they are
small on a WiFi link and so that a client that imports nothing from arpz can decode them as a
plain msgpack array whose first three elements are always ``[writer, seq, stamp_ns]``.
Control messages (``RobotStats``, ``Announce``) are msgpack maps, so fields can be added later
without breaking old decoders. The layouts are documented field by field in docs/protocol.md.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Final

import msgspec

#: The typed value of one sensor reading (seed 001, Table 1): floats for LIDAR, DHT11, IMU and
#: Ultrasonic; bool for Flame; the strings "detect"/"not detect" (PIR) and "light"/"dark" (Light).
ScalarValue = float | bool | str
#: ... and bytes: a camera frame or a point cloud (layouts in docs/sensors.md), carried by
#: ``LargeSample`` (msgspec decodes no union of str and bytes, and a small reading's decoder
#: should not pay for large ones)
SensorValue = ScalarValue | bytes

#: A command's value: a scalar, a string or a vector (for example a velocity ``[v, omega]``).
CommandValue = float | bool | str | list[float]


class Sample(msgspec.Struct, array_like=True, frozen=True):
    """One sensor reading, as published on ``.../sensor/{topic}``.

    ``seq`` counts the samples this writer SENT on this topic (1, 2, 3, ...): readings held back
    by the local cache take no number, so a gap in ``seq`` at the receiver is a real loss.
    """

    writer: str
    seq: int
    stamp_ns: int
    value: ScalarValue
    #: when the robot first read this value (the start of its run of equal readings; the
    #: receiver measures staleness from it); 0 = not given (then ``stamp_ns``)
    changed_ns: int = 0
    #: ``changed_ns`` of the oldest sample of this topic not yet acknowledged when this one was
    #: written (= ``changed_ns`` when all were): where staleness starts if samples before this
    #: one were lost; 0 = not given
    since_ns: int = 0


class LargeSample(msgspec.Struct, array_like=True, frozen=True):
    """A camera frame or point cloud: a ``Sample`` whose value is bytes, with the same layout
    and meaning of every field (on ``.../frames/{topic}`` through the reliable channel, or on
    ``.../sensor/{topic}`` in plain mode)."""

    writer: str
    seq: int
    stamp_ns: int
    value: bytes
    changed_ns: int = 0
    since_ns: int = 0


class MessageSample(msgspec.Struct, array_like=True, frozen=True):
    """A typed sensor's reading (``[[sensors]] type = "sensor_msgs/msg/NavSatFix"``): a ``Sample``
    whose value is a whole message of the topic's ROS 2 type, as the msgpack array of
    ``arpz.core.msgtypes`` (fields in definition order), with the same layout and meaning of
    every other field. The type is the one the robot announced for the topic (``TopicInfo``), so
    the value stays undecoded (``msgspec.Raw``) until a reader that knows it asks."""

    writer: str
    seq: int
    stamp_ns: int
    value: msgspec.Raw
    changed_ns: int = 0
    since_ns: int = 0


class Hello(msgspec.Struct, array_like=True, frozen=True):
    """The round-trip probe of seed 001 Figure 9, one hop of it.

    ``stage``: 0 origin -> CEDDP, 1 CEDDP -> relay, 2 relay -> CEDDP, 3 CEDDP -> origin.
    ``origin_seq`` and ``t0_ns`` are set once by the origin and never changed, so the origin can
    measure the whole round trip on its own clock.
    """

    writer: str
    seq: int
    stamp_ns: int
    origin: str
    origin_seq: int
    t0_ns: int
    stage: int


class Command(msgspec.Struct, array_like=True, frozen=True):
    """A command for a robot's actuation, as published on ``.../cmd/{name}``."""

    writer: str
    seq: int
    stamp_ns: int
    value: CommandValue


class MessageCommand(msgspec.Struct, array_like=True, frozen=True):
    """A typed command (an actuator's ``command_types``: ``geometry_msgs/msg/Twist`` on
    ``cmd_vel``): a ``Command`` whose value is a whole message of the type the robot announced for
    the command (``Announce.command_types``), as the msgpack array of ``arpz.core.msgtypes``."""

    writer: str
    seq: int
    stamp_ns: int
    value: msgspec.Raw


#: what ``CommandContract.sends`` says of a command sent as a value (not a message)
VALUE_COMMAND: Final = "value"


class CommandContract(msgspec.Struct, frozen=True):
    """What the CEDDP's planners send (the reply on ``ceddp/commands``): command name ->
    planner -> the ROS 2 type it sends, or ``VALUE_COMMAND``."""

    ceddp: str
    sends: dict[str, dict[str, str]] = msgspec.field(default_factory=dict)


def contract_clashes(
    contract: CommandContract, commands: Sequence[str], command_types: Mapping[str, str]
) -> list[str]:
    """Each planner command a robot acts on (``commands``) but takes as another type
    (``command_types``; a value when not named), in words."""
    clashes = []
    for name, by_planner in sorted(contract.sends.items()):
        if name not in commands:
            continue
        takes = command_types.get(name, VALUE_COMMAND)
        for planner, sends in sorted(by_planner.items()):
            if sends != takes:
                clashes.append(
                    f"planner {planner} sends {name} as {sends}, its actuator takes {takes}"
                )
    return clashes


class Telemetry(msgspec.Struct, array_like=True, frozen=True):
    """A simulated robot's TRUE pose, on ``.../telemetry``: for judging and drawing only, never
    for planning (the planner must make do with what the sensors say, as on real robots)."""

    writer: str
    seq: int
    stamp_ns: int
    x_m: float
    y_m: float
    theta_rad: float
    collided: bool


class ClockRequest(msgspec.Struct, array_like=True, frozen=True):
    """A robot's clock request on ``ceddp/clock`` (a Zenoh query's payload): t1, its clock at
    sending."""

    t1_ns: int


class ClockReply(msgspec.Struct, array_like=True, frozen=True):
    """The CEDDP's answer: the request's t1 echoed, t2 when the CEDDP received it and t3 when
    it replied, both on the CEDDP's clock."""

    t1_ns: int
    t2_ns: int
    t3_ns: int


class ServiceRequest(msgspec.Struct, frozen=True):
    """A call of a robot's service: the payload of a Zenoh query on ``srv/{name}`` (a map)."""

    #: the ROS 2 service type the caller means ("std_srvs/srv/Trigger"): a robot serving
    #: another type answers ``type_error`` without running its handler
    type: str
    #: the request message: msgpack of its type's wire Struct (``{type}_Request``), as
    #: ``MessageTypes.encode`` makes it
    request: msgspec.Raw
    #: the caller's timeout, ms: an answer later than this is counted a timeout at the robot
    timeout_ms: int
    #: who calls (a writer id such as "ceddp:5f0c2a9e41b7", or a tool's "tool:host:pid")
    caller: str = ""
    #: the caller's number of this call (echoed in every reply)
    id: int = 0


#: msgpack's nil: a ``ServiceReply`` without a response
NIL: Final = b"\xc0"
#: ``ServiceReply.status``: the robot took the request (sent at once, before the answer)
SERVICE_ACCEPTED: Final = "accepted"
#: the answer: ``response`` holds the response message
SERVICE_OK: Final = "ok"
#: the handler raised (``error``: its exception), or returned what does not fit the response type
SERVICE_FAILED: Final = "failed"
#: the request does not fit the request type, or names another service type (``error`` says
#: which field, or which type the robot serves)
SERVICE_TYPE_ERROR: Final = "type_error"
#: the robot serves no service of that name (``error`` lists those it serves)
SERVICE_UNKNOWN: Final = "unknown"
#: the service's queue is full: not run (``error`` says how many wait)
SERVICE_BUSY: Final = "busy"
#: the caller's timeout passed before the handler could start (it was not run)
SERVICE_TIMEOUT: Final = "timeout"
#: not a ``ServiceRequest`` at all
SERVICE_BAD_REQUEST: Final = "bad_request"


class ServiceReply(msgspec.Struct, frozen=True):
    """A robot's reply to a ``ServiceRequest`` (a map): first ``accepted`` when it queued the
    request, then the answer; or one refusal at once."""

    status: str
    #: the response message (status "ok"): msgpack of the response type's wire Struct; msgpack
    #: nil otherwise
    response: msgspec.Raw = msgspec.field(default_factory=lambda: msgspec.Raw(NIL))
    #: why it failed or was refused ("": ok)
    error: str = ""
    #: the service type the robot serves under this name ("": unknown service)
    type: str = ""
    #: the request's ``id``
    id: int = 0
    #: how long the handler ran, ms (the answer; None otherwise)
    handler_ms: float | None = None


class TopicCounters(msgspec.Struct, frozen=True, forbid_unknown_fields=False):
    """Per-topic counters a robot keeps: produced == sent + held_back + write_failures +
    driver_errors (every read of the driver is produced)."""

    produced: int = 0
    sent: int = 0
    held_back: int = 0
    last_seq: int = 0
    bytes_sent: int = 0
    #: sent per second over the last reporting interval
    rate_hz: float = 0.0
    #: read from the driver per second over the last interval (the scheduled rate, in effect)
    produced_rate_hz: float = 0.0
    #: reliable channel (zero without it): readings a full KEEP_ALL history refused (produced ==
    #: sent + held_back + write_failures), resends, samples answered with GAP (confirmed lost),
    #: KEEP_LAST overwrites of unacknowledged samples, offered-deadline misses
    write_failures: int = 0
    retransmitted: int = 0
    gapped: int = 0
    overwritten_unacked: int = 0
    deadline_missed: int = 0
    #: times the local cache forgot its last value because the newest sample could no longer
    #: be delivered (it expired unacknowledged), so the next reading is sent anyway
    cache_forgets: int = 0
    #: samples the history held when a reliable TRANSIENT_LOCAL reader matched (summed over
    #: matches): the most that late joiners could need resent
    history_offered: int = 0
    #: heartbeats the channel writer sent: what its recovery pacing cost in small messages
    heartbeats: int = 0
    #: of ``write_failures``: frames of a large sensor replaced by a newer one while the link
    #: was still taking the previous (arpz.robot.sensing.FrameSender)
    frames_skipped: int = 0
    #: sensing periods the scheduler could not run on time and skipped (it re-aligns when late)
    late_periods: int = 0
    #: reads that gave no reading (``produced == sent + held_back + write_failures +
    #: driver_errors``): the driver raised (``driver_exceptions``), or its value was refused
    #: (``values_refused``: a wrong type, a NaN or infinity under ``nan = "refuse"``)
    driver_errors: int = 0
    driver_exceptions: int = 0
    values_refused: int = 0
    #: reads that took longer than the sensor's period (the reading is sent all the same)
    late_reads: int = 0
    #: the last driver error or refusal, "ExceptionType: message" ("": none)
    last_driver_error: str = ""


class InboundCounters(msgspec.Struct, frozen=True, forbid_unknown_fields=False):
    """What a robot's reader of one CEDDP -> robot key saw (the downlink's half of the
    reconciliation: the CEDDP's writer reports what it sent within the match)."""

    delivered: int = 0
    lost: int = 0
    lifespan_expired: int = 0
    duplicates: int = 0
    #: samples refused because the CEDDP publishes them without the channel (or with it, in
    #: plain mode): INCOMPATIBLE_QOS
    refused: int = 0
    #: writers matched now
    matched: int = 0
    #: per matched writer (its guid): [first seq of the match, last seq accounted for,
    #: delivered, lost, lifespan expired] (the last three count the seqs in that range)
    writers: dict[str, list[int]] = msgspec.field(default_factory=dict)


class HelloStats(msgspec.Struct, frozen=True):
    """Hello round trips as measured by the origin robot's actuation."""

    sent: int = 0
    received: int = 0
    lost: int = 0
    outstanding: int = 0
    relayed: int = 0
    #: came back after being declared lost, or twice
    late: int = 0
    rtt_ms_p50: float | None = None
    rtt_ms_p99: float | None = None
    rtt_ms_max: float | None = None


class ClockStats(msgspec.Struct, frozen=True):
    """A robot's estimate of its clock against the CEDDP's (NTP-style exchanges on
    ``ceddp/clock``, the fastest of the last few: arpz/core/protocol/clock.py)."""

    #: the CEDDP's clock minus the robot's, ns (None: no reply yet); a robot stamp on the
    #: CEDDP's clock is ``stamp_ns + offset_ns``
    offset_ns: int | None = None
    #: the round trip of the exchange it comes from, ns: the offset is right within delay / 2
    delay_ns: int | None = None
    #: exchanges the estimate was chosen from
    samples: int = 0
    #: the robot's clock when that exchange ended (0: none)
    stamp_ns: int = 0
    #: requests sent and replies received since start
    requests: int = 0
    replies: int = 0


class ServiceCounters(msgspec.Struct, frozen=True, forbid_unknown_fields=False):
    """One service's calls as its robot counts them: every request taken is a call, and ends
    in exactly one of ok, failed, timeouts, type_errors or busy (``calls`` minus those is what
    is queued or running now). A handler that answers after the caller's timeout is counted
    a timeout, not ok (its late answer is still sent, and ignored)."""

    calls: int = 0
    ok: int = 0
    #: the handler raised, or returned what does not fit the response type
    failed: int = 0
    #: not answered within the caller's timeout (queued too long, or the handler too slow)
    timeouts: int = 0
    #: a request that does not fit the service's request type, or names another type
    type_errors: int = 0
    #: refused at once: the service's queue was full
    busy: int = 0
    #: the slowest handler run so far, ms (None: none ran)
    handler_ms_max: float | None = None
    #: the last failure's text ("": none)
    last_error: str = ""


class RobotStats(msgspec.Struct, frozen=True):
    """Counters a robot reports on ``.../stats`` periodically, and with final=True at exit."""

    robot: str
    incarnation: str
    stamp_ns: int
    final: bool
    topics: dict[str, TopicCounters]
    commands_received: int = 0
    command_decode_errors: int = 0
    hello: HelloStats | None = None
    #: CPU used by the robot agent process since the last report, in % of one core
    cpu_percent: float = 0.0
    #: the CEDDP QoS assignment in force (epoch 0: none, the robot runs its own config)
    qos_epoch: int = 0
    qos_rate_hz: float | None = None
    qos_depth: int | None = None
    #: per CEDDP -> robot key (``cmd/velocity``, ``cmd/hello``, ``ceddp/qos``, by the key's
    #: last chunks): the downlink's counters
    inbound: dict[str, InboundCounters] = msgspec.field(default_factory=dict)
    #: commands dropped because they arrived past the command lifespan
    commands_expired: int = 0
    #: command watchdog: safe stops per command name, and the names stopped now
    watchdog_stops: dict[str, int] = msgspec.field(default_factory=dict)
    watchdog_stopped: list[str] = msgspec.field(default_factory=list)
    #: INCOMPATIBLE_QOS seen by the robot: "what: why" lines (empty when all matched)
    incompatible_qos: list[str] = msgspec.field(default_factory=list)
    #: "channel" or "none"
    mode: str = "channel"
    #: the robot's clock against the CEDDP's (None: clock sync off, or an older robot)
    clock: ClockStats | None = None
    #: the robot's arpz and eclipse-zenoh versions ("": an older robot)
    arpz_version: str = ""
    zenoh_version: str = ""
    #: sensor messages sent in bundles, and the bundles (one Zenoh message per scheduler tick,
    #: docs/protocol.md "Bundles"); bundles the link refused, whose messages the channel recovers
    bundled_messages: int = 0
    bundles: int = 0
    bundle_put_failures: int = 0
    #: sensors that gave no reading (only driver errors, or none read) for the whole last
    #: reporting interval and at least two of their periods
    silent_sensors: list[str] = msgspec.field(default_factory=list)
    #: the robot's wall clock when this incarnation started (0: an older robot): of two
    #: processes running with one robot_id, the CEDDP keeps the one that started first
    started_ns: int = 0
    #: per service the robot serves (``[[services]]``, docs/nodes.md "Services"): its calls
    services: dict[str, ServiceCounters] = msgspec.field(default_factory=dict)


class TopicRate(msgspec.Struct, frozen=True):
    """What the CEDDP measured arriving on one robot topic over the last reporting interval."""

    robot: str
    topic: str
    rate_hz: float
    bytes_per_s: float
    #: samples of the topic lost so far (sequence gaps and what was sent before the CEDDP heard
    #: the writer)
    lost: int = 0


class CeddpStats(msgspec.Struct, frozen=True):
    """Periodic report of the CEDDP process on ``arpz/{fleet}/ceddp/stats``."""

    stamp_ns: int
    cpu_percent: float
    topics: list[TopicRate]
    #: sensor samples ingested since start
    processed: int = 0
    #: share of the interval the sensor path's thread worked (did not wait for samples), 0..1
    load: float = 0.0
    #: the longest a sample waited in the CEDDP over the interval, from the router's receipt
    #: to the sensor path taking it, ms: its ingest backlog in time (None: not measured, the
    #: raw path or an older CEDDP)
    ingest_backlog_ms: float | None = None
    #: pooled p99 latency (robot stamp to ingest) of the interval, ms; None: nothing arrived
    latency_ms_p99: float | None = None
    #: measured capacity (samples per busy second) and the fleet's budget in force (samples/s;
    #: None: no budget), arpz/ceddp/overload.py
    capacity_hz: float | None = None
    budget_hz: float | None = None
    #: dashboard frames dropped since start (the Rerun thread fell behind)
    dashboard_dropped: int = 0
    #: the CEDDP's arpz and eclipse-zenoh versions ("": an older CEDDP)
    arpz_version: str = ""
    zenoh_version: str = ""
    #: whether the CEDDP's Zenoh config carries an enabled ``access_control`` section, and
    #: whether it sets up TLS (None: not known, an older CEDDP)
    access_control: bool | None = None
    tls: bool | None = None
    #: INCOMPATIBLE_QOS the CEDDP sees, "robot: what: why" lines
    incompatible_qos: list[str] = msgspec.field(default_factory=list)
    #: latencies are corrected by each robot's clock offset (arpz/ceddp/clock_service.py), and
    #: the bound on |offset| past which a robot is flagged (None: an older CEDDP)
    clock_corrected: bool = False
    clock_max_offset_ms: float | None = None
    #: robots whose |offset| exceeds the bound now
    clock_flagged: list[str] = msgspec.field(default_factory=list)
    #: robot ids two processes run with now ("robot: kept incarnation, dropped incarnation"):
    #: the newer one's samples are dropped
    duplicate_robots: list[str] = msgspec.field(default_factory=list)


class TopicInfo(msgspec.Struct, frozen=True):
    topic: str
    kind: str
    rate_hz: float
    value_type: str
    #: the sensor's priority for the per-topic QoS optimiser, and the fastest it can be read
    #: (None: no limit); older robots leave them out
    priority: float = 1.0
    max_rate_hz: float | None = None
    #: the rate the sensor is configured at (its TOML ``rate_hz``): an assignment never raises
    #: a sensor above it (``rate_hz`` is the rate in force, which an assignment lowers); None:
    #: an older robot
    configured_rate_hz: float | None = None
    #: the topic's ROS 2 message type and its RIHS01 hash as ROS 2 computes it (a typed sensor's
    #: own; a scalar kind's standard type, docs/protocol.md); "": an older robot
    msg_type: str = ""
    type_hash: str = ""


class Announce(msgspec.Struct, frozen=True):
    """What a robot publishes and listens to; the CEDDP counts topics per robot from this."""

    robot: str
    incarnation: str
    sensors: list[TopicInfo]
    commands: list[str]
    #: "channel" (every key through the reliable channel) or "none" (plain puts)
    mode: str = "channel"
    #: the robot's clock estimate when it announced (the first one precedes its first reading,
    #: so the CEDDP can correct latencies from the start)
    clock: ClockStats | None = None
    #: the typed commands among ``commands``: name -> the ROS 2 type it accepts (the others take
    #: a value: a float, bool, string or list of floats)
    command_types: dict[str, str] = msgspec.field(default_factory=dict)
    #: the services the robot serves, name -> ROS 2 service type ("std_srvs/srv/Trigger"), on
    #: ``srv/{name}`` (docs/protocol.md "Services")
    services: dict[str, str] = msgspec.field(default_factory=dict)


class RobotQos(msgspec.Struct, frozen=True):
    """What one robot must run at: every sensor at ``rate_hz`` (DEADLINE period ``deadline_s``)
    with writer history depth ``depth`` (KEEP_LAST)."""

    rate_hz: float
    deadline_s: float
    depth: int
    #: the sensor writers' heartbeat period, set by the closed QoS loop from the robot's measured
    #: link (a lost last sample waits for a heartbeat); None: the robot's own [sensor_qos] period
    heartbeat_period_s: float | None = None


class QosAssignmentMsg(msgspec.Struct, frozen=True):
    """The CEDDP's QoS assignment for the whole fleet, on ``arpz/{fleet}/ceddp/qos``.

    ``epoch`` grows with every new assignment of this CEDDP incarnation; a robot answers each one
    on its ``.../qos`` key with a ``QosAck``.
    """

    ceddp: str
    epoch: int
    stamp_ns: int
    reason: str
    t_avg: float
    topics_per_robot: dict[str, int]
    robots: dict[str, RobotQos]
    #: the fleet's rate budget of the overload governor this assignment fits (samples/s), or
    #: None when the configured limits alone apply
    budget_hz: float | None = None
    #: "fleet" (seed 001: ``robots`` alone) or "per_topic": then ``topics`` gives, per robot,
    #: each sensor topic's own rate, deadline and depth (``robots`` keeps a fleet-wide summary
    #: for older robots: the mean rate of the robot's topics and its largest depth)
    mode: str = "fleet"
    topics: dict[str, dict[str, RobotQos]] = msgspec.field(default_factory=dict)


class QosAck(msgspec.Struct, frozen=True):
    """A robot's answer to an assignment: applied, or refused with the reason."""

    robot: str
    incarnation: str
    ceddp: str
    epoch: int
    stamp_ns: int
    status: str
    reason: str
    rate_hz: float
    depth: int
    #: the heartbeat period the robot's first sensor writer runs at after this answer (None:
    #: no channel writer)
    heartbeat_period_s: float | None = None


class RobotConfiguration(msgspec.Struct, frozen=True):
    """What seed 002's configurator asks of one robot: each listed sensor topic sampled at its
    rate, and each listed computation run "robot" or "ceddp" (arpz/robot/configuration.py)."""

    rates_hz: dict[str, float] = msgspec.field(default_factory=dict)
    computations: dict[str, str] = msgspec.field(default_factory=dict)


class ConfigurationMsg(msgspec.Struct, frozen=True):
    """A configurator's solution for the fleet, on ``arpz/{fleet}/ceddp/config`` (a key of its
    own beside the QoS assignment, latched: a robot that joins later receives it too)."""

    sender: str
    epoch: int
    stamp_ns: int
    #: what was solved (model, problem, method), for the robots' logs
    source: str
    robots: dict[str, RobotConfiguration]


class ConfigurationAck(msgspec.Struct, frozen=True):
    """A robot's answer on ``robot/{robot}/config/ack``: what it runs now, what it refused."""

    robot: str
    incarnation: str
    sender: str
    epoch: int
    stamp_ns: int
    rates_hz: dict[str, float]
    computations: dict[str, str]
    #: "what: why" for every item it could not apply
    refused: list[str] = msgspec.field(default_factory=list)


#: what decoding untrusted bytes may raise: msgspec raises UnicodeDecodeError, not DecodeError,
#: for a msgpack string that is not valid UTF-8 (found by the property tests)
#: what a decoder raises on bad bytes; RecursionError: msgpack nested deeper than msgspec follows
DECODE_ERRORS: Final = (msgspec.DecodeError, UnicodeDecodeError, RecursionError)

SAMPLE_ENCODER: Final = msgspec.msgpack.Encoder()
SAMPLE_DECODER: Final = msgspec.msgpack.Decoder(Sample)
LARGE_SAMPLE_DECODER: Final = msgspec.msgpack.Decoder(LargeSample)
MESSAGE_SAMPLE_DECODER: Final = msgspec.msgpack.Decoder(MessageSample)
HELLO_DECODER: Final = msgspec.msgpack.Decoder(Hello)
COMMAND_DECODER: Final = msgspec.msgpack.Decoder(Command)
MESSAGE_COMMAND_DECODER: Final = msgspec.msgpack.Decoder(MessageCommand)
COMMAND_CONTRACT_DECODER: Final = msgspec.msgpack.Decoder(CommandContract)
STATS_DECODER: Final = msgspec.msgpack.Decoder(RobotStats)
ANNOUNCE_DECODER: Final = msgspec.msgpack.Decoder(Announce)
CEDDP_STATS_DECODER: Final = msgspec.msgpack.Decoder(CeddpStats)
QOS_ASSIGNMENT_DECODER: Final = msgspec.msgpack.Decoder(QosAssignmentMsg)
QOS_ACK_DECODER: Final = msgspec.msgpack.Decoder(QosAck)
CONFIGURATION_DECODER: Final = msgspec.msgpack.Decoder(ConfigurationMsg)
CONFIGURATION_ACK_DECODER: Final = msgspec.msgpack.Decoder(ConfigurationAck)
TELEMETRY_DECODER: Final = msgspec.msgpack.Decoder(Telemetry)
CLOCK_REQUEST_DECODER: Final = msgspec.msgpack.Decoder(ClockRequest)
CLOCK_REPLY_DECODER: Final = msgspec.msgpack.Decoder(ClockReply)
SERVICE_REQUEST_DECODER: Final = msgspec.msgpack.Decoder(ServiceRequest)
SERVICE_REPLY_DECODER: Final = msgspec.msgpack.Decoder(ServiceReply)


def same_value(a: SensorValue, b: SensorValue, tolerance: float = 0.0) -> bool:
    """Equal in type and value (floats within ``tolerance``): True and 1.0 are NOT the same
    reading, nor are "1" and 1.0. Used by the robot's local cache and the CEDDP's cache control."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float) and isinstance(b, float):
        return a == b or abs(a - b) <= tolerance
    return a == b


def encode(message: msgspec.Struct) -> bytes:
    return SAMPLE_ENCODER.encode(message)


def new_incarnation() -> str:
    """A random id for one run of a process: a restarted writer is a new writer."""
    return os.urandom(6).hex()


def writer_id(robot: str, incarnation: str) -> str:
    return f"{robot}:{incarnation}"
