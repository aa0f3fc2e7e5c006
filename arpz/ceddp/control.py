"""The CEDDP's control path: what the robots report and whether they are there.

``ControlWorker`` owns the fleet's registry (one ``RobotRecord`` per robot) and the thread that
keeps it: the robots' reports (stats, announcements, QoS acks, telemetry), their presence and
mode tokens, INCOMPATIBLE_QOS, and QoS requests. They arrive by callback, wait in a bounded
``ControlQueue`` (the latest per key), and run one at a time on the control worker, under the
ingest lock (the summary and the metrics read the registry under it too). What they change in
the fleet follows from here: a robot's command writers open and close, the cache forgets a robot
that left, and problem (6) is re-solved when the fleet's topics change.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import msgspec

from arpz.ceddp.clock_service import ClockWatch
from arpz.ceddp.control_queue import ControlQueue
from arpz.ceddp.downlink import Downlink
from arpz.ceddp.ingest import Ingest
from arpz.ceddp.link_meter import channel_round_trip_s
from arpz.ceddp.overload import BudgetChange
from arpz.ceddp.planner import Planner
from arpz.ceddp.qos_control import QosController
from arpz.ceddp.summary import RobotReport
from arpz.channel import QosPolicyKind, Reader
from arpz.channel.io import Outlet
from arpz.core import keys
from arpz.core.config import MESSAGE_KIND, CeddpConfig
from arpz.core.messages import (
    ANNOUNCE_DECODER,
    DECODE_ERRORS,
    QOS_ACK_DECODER,
    STATS_DECODER,
    TELEMETRY_DECODER,
    Announce,
    CommandContract,
    RobotStats,
    contract_clashes,
    encode,
    writer_id,
)
from arpz.core.throttled_log import ThrottledLog

log = logging.getLogger(__name__)
#: bad reports, refused items and failures: one line per cause per 10 s, never one per message
throttled = ThrottledLog(log)

REPORT, PRESENCE, QOS_REQUEST, MODE, INCOMPATIBLE, BUDGET = 1, 2, 3, 4, 5, 6
KIND_NAMES = {
    BUDGET: "budget",
    REPORT: "report",
    PRESENCE: "presence",
    QOS_REQUEST: "qos_request",
    MODE: "mode",
    INCOMPATIBLE: "incompatible",
}
_REPORT_KINDS = ("stats", "announce", "qos", "telemetry")
#: incarnations of one robot reported separately in the summary (the ingest tracks as many)
MAX_INCARNATIONS = 16
#: a robot's outages (away and back as the same incarnation) kept for the summary
MAX_OUTAGES = 64
#: a second process with a robot's id counts as running while it reported this recently
DUPLICATE_LIVE_S = 10.0

BUDGET_DECODER = msgspec.msgpack.Decoder(BudgetChange)

#: (text, level) -> None: a fleet event, for the log, the dashboard and the summary
EventSink = Callable[[str, str], None]


@dataclass
class Duplicate:
    """An incarnation of a robot that ran while another was followed: two processes with one
    robot_id. Its samples are dropped (``Ingest.drop_writer``) until the one followed stops."""

    incarnation: str
    #: when it was found (monotonic s) and when it last reported
    since_s: float
    last_report_s: float
    #: its reports since it was found (never applied)
    reports: int = 0
    #: its final report came: it stopped
    stopped: bool = False

    def live(self, now_s: float) -> bool:
        return not self.stopped and now_s - self.last_report_s < DUPLICATE_LIVE_S


@dataclass
class RobotRecord:
    """What the CEDDP knows of one robot beyond its topics."""

    alive: bool = False
    joins: int = 0
    leaves: int = 0
    stats: RobotStats | None = None
    announce: Announce | None = None
    #: eq. 1 of seed 001 for this robot's current incarnation (None while it is away)
    topic_count: int | None = None
    #: a report that could not be decoded
    control_decode_errors: int = 0
    #: INCOMPATIBLE_QOS with this robot ("what: why"); it stays out of the optimiser meanwhile
    incompatible: list[str] = field(default_factory=list)
    #: the robot's mode token ("channel" / "none"), None until seen
    mode: str | None = None
    #: the last report of each incarnation, at most MAX_INCARNATIONS (the oldest dropped)
    incarnations: dict[str, RobotStats] = field(default_factory=dict)
    #: when its presence last vanished (monotonic s; None while present)
    away_since_s: float | None = None
    #: it came back after being away this long (s) and its next report says whether as the
    #: same incarnation (a dead zone, a roam) or a new one (a restart); None: nothing pending
    back_after_s: float | None = None
    #: the incarnation it had when it went away
    away_incarnation: str = ""
    #: times it was away and came back as the same incarnation, with how long (s), newest
    #: MAX_OUTAGES
    outages: list[float] = field(default_factory=list)
    #: the incarnation followed now: its reports are the robot's, its samples counted ("":
    #: none reported yet); a report of a new one is a restart, and it is followed from then on
    incarnation: str = ""
    #: typed topics this CEDDP cannot decode, each said once in the event log
    type_warnings: set[str] = field(default_factory=set)
    #: every incarnation reported, with when it was first (monotonic s), at most
    #: MAX_INCARNATIONS
    seen: dict[str, float] = field(default_factory=dict)
    #: incarnations found running beside the one followed (the same robot_id twice)
    duplicates: dict[str, Duplicate] = field(default_factory=dict)
    #: when the followed incarnation last reported (monotonic s)
    last_report_s: float = 0.0
    #: per topic, (decode errors, cache-control discards) when the followed incarnation took
    #: over: the live views count its own from there
    baselines: dict[str, tuple[int, int]] = field(default_factory=dict)

    def as_report(self) -> RobotReport:
        now = time.monotonic()
        return RobotReport(
            alive=self.alive,
            joins=self.joins,
            leaves=self.leaves,
            control_decode_errors=self.control_decode_errors,
            stats=self.stats,
            incompatible=list(self.incompatible),
            incarnations=dict(self.incarnations),
            outages=list(self.outages),
            incarnation=self.incarnation,
            duplicates={
                name: {
                    "running": d.live(now),
                    "found_s_ago": round(now - d.since_s, 3),
                    "reports_ignored": d.reports,
                }
                for name, d in self.duplicates.items()
            },
        )

    def live_duplicates(self, now_s: float) -> list[str]:
        return [name for name, d in self.duplicates.items() if d.live(now_s)]


@dataclass
class ControlCounters:
    unknown_control_keys: int = 0
    #: reports refused before decoding for exceeding max_report_bytes
    reports_oversize: int = 0
    #: reports of robots beyond max_robots (invented ids): refused, no record made
    reports_over_limit: int = 0


class ControlWorker:
    """Thread: ``run`` is the control worker (``arpz-control``); the ``on_*`` methods are Zenoh
    callbacks and only queue."""

    def __init__(
        self,
        config: CeddpConfig,
        ingest: Ingest,
        sink: Downlink,
        planners: list[Planner],
        qos: QosController | None,
        event: EventSink,
        *,
        clock: ClockWatch | None = None,
        command_contract: Callable[[], CommandContract] | None = None,
    ) -> None:
        self.config = config
        #: takes each robot's clock estimate from its stats and announcements
        self.clock = clock
        #: what the team's planners send: a robot announcing another type for one of them is
        #: said once in the event log (it refused to start if it could ask; docs/nodes.md)
        self.command_contract = command_contract or (lambda: CommandContract(""))
        self.ingest = ingest
        self.sink = sink
        self.planners = planners
        self.qos = qos
        if qos is not None:
            # the loss-aware depth bounds recovery with the sensor channel's own timings
            qos.channel = config.profile("sensor") or qos.channel
        self._event = event
        self.robots: dict[str, RobotRecord] = {}
        self.counters = ControlCounters()
        self.queue = ControlQueue(config.control_queue_limit)
        #: where assignments go (opened by the server when it runs QoS control)
        self.qos_out: Outlet | None = None
        #: budget changes the overload governor made while QoS control is off (not applied)
        self.unapplied_budgets = 0
        #: the CEDDP's sensor reader, which follows the assigned depth (channel mode)
        self.sensor_reader: Reader | None = None

    # -- callbacks: only queue ------------------------------------------------------------------

    def on_report(self, key: str, payload: bytes) -> None:
        cfg = self.config
        if len(payload) > cfg.max_report_bytes:
            self.counters.reports_oversize += 1
            throttled.warning(
                "oversize report",
                "report of %d bytes on %s refused (max_report_bytes %d)",
                len(payload),
                key,
                cfg.max_report_bytes,
            )
            return
        parsed = keys.parse_robot_key(key)
        if parsed is None or parsed[1] not in _REPORT_KINDS or parsed[2]:
            # counted here, not queued: the queue keeps one item per key
            self.counters.unknown_control_keys += 1
            return
        self.put(REPORT, key, payload)

    def on_presence(self, key: str, alive: bool) -> None:
        self.put(PRESENCE, key, b"\x01" if alive else b"")

    def on_mode(self, key: str, alive: bool) -> None:
        self.put(MODE, key, b"\x01" if alive else b"")

    def on_qos_request(self, key: str, payload: bytes, _attachment: bytes | None) -> None:
        self.put(QOS_REQUEST, key, payload)

    def on_incompatible(self, key: str, policy: QosPolicyKind) -> None:
        self.put(INCOMPATIBLE, key, policy.value.encode())

    def put(self, kind: int, key: str, payload: bytes) -> None:
        if not self.queue.put(kind, key, payload):
            throttled.warning(
                "control queue full",
                "%s on %s dropped: %d reports and events already wait (control_queue_limit)",
                KIND_NAMES[kind],
                key,
                self.queue.limit,
            )

    # -- the worker -----------------------------------------------------------------------------

    def run(self) -> None:
        """Until the queue is closed and drained."""
        while (item := self.queue.get()) is not None:
            kind, key, payload = item
            with self.ingest.lock:
                try:
                    if kind == REPORT:
                        self._handle_report(key, payload)
                    elif kind == PRESENCE:
                        self._handle_presence(key, bool(payload))
                    elif kind == MODE:
                        self._handle_mode(key, bool(payload))
                    elif kind == INCOMPATIBLE:
                        self.mark_incompatible(key, payload.decode())
                    elif kind == BUDGET:
                        self._apply_budget(BUDGET_DECODER.decode(payload))
                    else:
                        self.reassign_qos("requested", force=True)
                except Exception:  # a bug in one handler must not stop the control worker
                    throttled.exception(
                        f"control {kind} failed", "control message failed on %s", key
                    )

    def _handle_report(self, key: str, payload: bytes) -> None:
        parsed = keys.parse_robot_key(key)
        if parsed is None or parsed[1] not in _REPORT_KINDS or parsed[2]:
            self.counters.unknown_control_keys += 1
            return
        robot, kind, _ = parsed
        record = self.robots.get(robot)
        if record is None:
            if len(self.robots) >= self.config.max_robots:
                self.counters.reports_over_limit += 1
                return
            record = self.robots.setdefault(robot, RobotRecord())
        try:
            if kind == "stats":
                stats = STATS_DECODER.decode(payload)
                if record.back_after_s is not None:
                    self._classify_return(robot, record, stats.incarnation)
                followed = self._follows(robot, record, stats.incarnation, stats)
                known = record.incarnations.get(stats.incarnation)
                if known is None or not known.final or stats.final:
                    record.incarnations[stats.incarnation] = stats
                    while len(record.incarnations) > MAX_INCARNATIONS:
                        del record.incarnations[next(iter(record.incarnations))]
                if not followed:
                    return  # a second process's: kept per incarnation, never the robot's
                current = record.stats
                if (
                    current is None
                    or current.incarnation != stats.incarnation
                    or not current.final
                    or stats.final
                ):
                    record.stats = stats
                if self.clock is not None:
                    self.clock.observe(robot, stats.clock)
                if self.qos is not None and record.alive:
                    self._measure_link(stats)
            elif kind == "announce":
                announce = ANNOUNCE_DECODER.decode(payload)
                if not self._follows(robot, record, announce.incarnation, None):
                    return
                record.announce = announce
                if self.qos is not None:
                    self.qos.set_sensors(robot, record.announce.sensors)
                sensors = record.announce.sensors
                refused = self.ingest.set_kinds(
                    robot,
                    {t.topic: t.kind for t in sensors},
                    {t.topic: (t.msg_type, t.type_hash) for t in sensors if t.kind == MESSAGE_KIND},
                )
                contract = self.command_contract()
                clashes = contract_clashes(
                    contract, record.announce.commands, record.announce.command_types
                )
                refused += [
                    f"robot {robot}: {clash}: those commands cannot reach it" for clash in clashes
                ]
                for why in refused:
                    if why not in record.type_warnings:
                        record.type_warnings.add(why)
                        self._event(why, "WARN")
                if self.clock is not None:
                    self.clock.observe(robot, record.announce.clock)
                if record.alive:
                    self.sink.open_robot(robot, list(record.announce.commands))
                count = len(record.announce.sensors) + len(record.announce.commands)
                if count != record.topic_count:
                    record.topic_count = count
                    self.reassign_qos(f"robot {robot} uses {count} topics")
            elif kind == "telemetry":
                telemetry = TELEMETRY_DECODER.decode(payload)
                for planner in self.planners:
                    planner.on_telemetry(robot, telemetry)
            elif self.qos is not None:
                self._event(self.qos.on_ack(QOS_ACK_DECODER.decode(payload)), "INFO")
        except DECODE_ERRORS as exc:
            record.control_decode_errors += 1
            throttled.warning(
                f"undecodable {kind} from {robot}",
                "undecodable %s report from %s (%d so far): %s",
                kind,
                robot,
                record.control_decode_errors,
                exc,
            )

    # -- incarnations: restarts, and one robot_id in two processes ----------------------------

    def _follows(
        self, robot: str, record: RobotRecord, incarnation: str, stats: RobotStats | None
    ) -> bool:
        """Whether a report of ``incarnation`` is the robot's (the incarnation followed) or
        a second process's with the same robot_id, whose reports are kept apart and whose
        samples are dropped. A new incarnation is a restart: followed from its first report.
        One that was followed before and reports again (a new stats report, not its final
        one) runs beside the newer: the one that started first is followed, the other is a
        duplicate, loudly."""
        now = time.monotonic()
        duplicate = record.duplicates.get(incarnation)
        if duplicate is not None:
            duplicate.reports += 1
            duplicate.last_report_s = now
            if stats is not None and stats.final and not duplicate.stopped:
                duplicate.stopped = True
                self._event(
                    f"robot {robot}: the second process (incarnation {incarnation}) stopped; "
                    f"{self._dropped(robot, incarnation)} of its samples were dropped",
                    "INFO",
                )
            if not self._followed_gone(record, now):
                return False
            # the process followed stopped: the other one is the robot now
            del record.duplicates[incarnation]
            self.ingest.keep_writer(robot, writer_id(robot, incarnation))
            self._event(
                f"robot {robot}: incarnation {record.incarnation} stopped, so the other "
                f"process (incarnation {incarnation}) is followed from now on",
                "WARN",
            )
            self._switch(robot, record, incarnation, now)
            return True
        if incarnation == record.incarnation:
            record.last_report_s = now
            return True
        if incarnation not in record.seen:
            record.seen[incarnation] = now
            while len(record.seen) > MAX_INCARNATIONS:
                del record.seen[next(iter(record.seen))]
            self._switch(robot, record, incarnation, now)
            return True
        # an incarnation followed before another, reporting again
        known = record.incarnations.get(incarnation)
        if stats is None or stats.final or (known is not None and stats.stamp_ns <= known.stamp_ns):
            return False  # an announcement again, its last words, or a report we had
        self._duplicate_found(robot, record, incarnation, stats, now)
        return record.incarnation == incarnation

    @staticmethod
    def _followed_gone(record: RobotRecord, now: float) -> bool:
        stats = record.stats
        finished = stats is not None and stats.incarnation == record.incarnation and stats.final
        return finished or now - record.last_report_s >= DUPLICATE_LIVE_S

    def _switch(self, robot: str, record: RobotRecord, incarnation: str, now: float) -> None:
        """Follow ``incarnation`` from now on: the live views count its topics from here."""
        record.baselines = (
            {
                m.topic: (m.decode_errors, self.ingest.cache_counters(robot, m.topic).hits)
                for m in self.ingest.robot_topics(robot)
            }
            if record.incarnation
            else {}
        )
        record.incarnation = incarnation
        record.last_report_s = now
        record.stats = record.incarnations.get(incarnation)

    def _duplicate_found(
        self, robot: str, record: RobotRecord, incarnation: str, stats: RobotStats, now: float
    ) -> None:
        """``incarnation`` runs beside the one followed: keep the one that started first
        (each robot's start on the CEDDP's clock; else the one reported first)."""
        other = record.incarnation
        other_stats = record.incarnations.get(other)
        mine, theirs = _started_ns(stats), _started_ns(other_stats)
        if mine is not None and theirs is not None:
            keep_mine = mine <= theirs
        else:
            keep_mine = record.seen.get(incarnation, now) <= record.seen.get(other, now)
        keep, drop = (incarnation, other) if keep_mine else (other, incarnation)
        if keep != record.incarnation:
            self._switch(robot, record, keep, now)
        record.duplicates[drop] = Duplicate(drop, since_s=now, last_report_s=now)
        while len(record.duplicates) > MAX_INCARNATIONS:
            del record.duplicates[next(iter(record.duplicates))]
        self.ingest.drop_writer(robot, writer_id(robot, drop))
        started = {
            name: _started_text(s) for name, s in ((incarnation, stats), (other, other_stats))
        }
        self._event(
            f"robot {robot}: two processes run as {robot}: incarnation {keep}{started[keep]} "
            f"and incarnation {drop}{started[drop]}; {drop}'s samples are dropped from now on "
            "(counted), and both act on every command: stop one, and give each robot its own "
            "robot_id",
            "ERROR",
        )

    def _dropped(self, robot: str, incarnation: str) -> int:
        writer = writer_id(robot, incarnation)
        return sum(m.duplicate_dropped.get(writer, 0) for m in self.ingest.robot_topics(robot))

    def _measure_link(self, stats: RobotStats) -> None:
        """A report measures the robot's link (resends per send) and, with the sensor reader's
        NACKs, the loss bursts; past the hysteresis the QoS problem is re-solved."""
        assert self.qos is not None
        counts = None
        rtt = None
        if self.sensor_reader is not None:
            reader = self.sensor_reader.stats()
            counts = (reader.retransmitted, reader.nacks)
            rtt = channel_round_trip_s(self.sensor_reader.round_trips(), stats.robot)
        reason = self.qos.observe(stats, counts, rtt)
        if reason is not None:
            self.reassign_qos(reason, force=True)

    def _handle_mode(self, key: str, alive: bool) -> None:
        """A robot's mode token: INCOMPATIBLE_QOS when it is not this CEDDP's mode."""
        parsed = keys.parse_robot_key(key)
        if parsed is None or not alive or len(self.robots) >= self.config.max_robots:
            return
        robot, _, mode = parsed
        record = self.robots.setdefault(robot, RobotRecord())
        record.mode = mode
        if mode != self.config.reliability:
            self.mark_incompatible(
                key,
                f"mode: robot '{mode}', CEDDP '{self.config.reliability}' (set reliability the "
                "same on both sides)",
            )

    def mark_incompatible(self, key: str, why: str) -> None:
        """INCOMPATIBLE_QOS with the robot of ``key``: reported, and out of the optimiser."""
        parsed = keys.parse_robot_key(key)
        if parsed is None:
            return
        robot = parsed[0]
        record = self.robots.get(robot)
        if record is None:
            if len(self.robots) >= self.config.max_robots:
                return
            record = self.robots.setdefault(robot, RobotRecord())
        what = "/".join(key.split("/")[4:]) or "mode"
        text = f"{what}: {why}"
        if text in record.incompatible or len(record.incompatible) >= 16:
            return
        record.incompatible.append(text)
        self._event(f"robot {robot}: INCOMPATIBLE_QOS {text}; its data is refused", "ERROR")
        if record.topic_count is not None and len(record.incompatible) == 1:
            self.reassign_qos(f"robot {robot} is incompatible")

    def _handle_presence(self, key: str, alive: bool) -> None:
        parsed = keys.parse_robot_key(key)
        if parsed is None:
            return
        robot = parsed[0]
        record = self.robots.setdefault(robot, RobotRecord())
        if record.alive == alive:
            return
        record.alive = alive
        now = time.monotonic()
        if alive:
            record.joins += 1
            if record.away_since_s is None:
                self._event(f"robot {robot} joined", "INFO")
            else:
                # the next report tells a dead zone or a roam (same incarnation) from a restart
                record.back_after_s = now - record.away_since_s
                record.away_since_s = None
        else:
            record.leaves += 1
            record.away_since_s = now
            record.back_after_s = None
            record.away_incarnation = record.stats.incarnation if record.stats else ""
            if record.stats is not None and record.stats.final:
                self._event(f"robot {robot} left (it stopped: its final report is in)", "INFO")
            else:
                self._event(
                    f"robot {robot} unreachable: its session ended (a dead zone, a roam or a "
                    "crash); its channel state is kept for it to come back",
                    "WARN",
                )
        if alive and record.announce is not None:
            self.sink.open_robot(robot, list(record.announce.commands))
        if not alive:
            self.sink.robot_away(robot)
            self.ingest.cache_control.forget(robot)
            if record.topic_count is not None:
                record.topic_count = None
                self.reassign_qos(f"robot {robot} left")
        elif record.topic_count is not None:
            # its announcement came first (reports and presence travel separately)
            self.reassign_qos(f"robot {robot} joined with {record.topic_count} topics")
        for planner in self.planners:
            planner.on_robot(robot, alive)

    def _classify_return(self, robot: str, record: RobotRecord, incarnation: str) -> None:
        """The first report after a robot came back: one event for the whole absence."""
        away_s = record.back_after_s or 0.0
        record.back_after_s = None
        # reports seen before it went away name the incarnation (all of them: it may have gone
        # before its first report of the run reached us)
        if incarnation == record.away_incarnation or incarnation in record.incarnations:
            record.outages.append(away_s)
            del record.outages[:-MAX_OUTAGES]
            self._event(
                f"robot {robot} back after {away_s:.1f} s unreachable (same incarnation: a "
                "dead zone or a roam); its matches resumed",
                "WARN",
            )
        else:
            self._event(
                f"robot {robot} joined as a new incarnation {incarnation} after {away_s:.1f} s "
                f"away (restarted; was {record.away_incarnation or 'unknown'})",
                "INFO",
            )

    def on_budget(self, change: BudgetChange) -> None:
        """The overload governor changed the fleet's budget (metrics thread): queued, so that
        the re-solve runs on this worker like every other; a newer change replaces a waiting
        one."""
        self.put(BUDGET, "budget", msgspec.msgpack.encode(change))

    def _apply_budget(self, change: BudgetChange) -> None:
        if self.qos is None:
            # the governor keeps cutting while nothing changes: one event, then the log only
            self.unapplied_budgets += 1
            text = (
                f"{change.reason}; QoS control is off ([qos] enabled = false), so the fleet's "
                "rates stay as configured"
            )
            if self.unapplied_budgets == 1:
                self._event(text, "WARN")
            else:
                throttled.warning("budget without QoS control", "%s", text)
            return
        self.qos.budget_hz = change.budget_hz
        self._event(change.reason, "WARN" if change.budget_hz is not None else "INFO")
        self.reassign_qos(change.reason, force=True)

    def reassign_qos(self, reason: str, *, force: bool = False) -> None:
        """Re-solve problem (6) for the robots present now; publish if the answer changed."""
        if self.qos is None:
            return
        topics = {
            robot: record.topic_count
            for robot, record in self.robots.items()
            if record.alive and record.topic_count is not None and not record.incompatible
        }
        before = len(self.qos.errors)
        message = self.qos.update(topics, reason, force=force)
        if message is None:
            if len(self.qos.errors) > before:
                self._event(self.qos.errors[-1], "ERROR")
            return
        assert self.qos_out is not None, "the server opens the assignment writer at start"
        self.qos_out.send(encode(message), message.stamp_ns)
        if self.sensor_reader is not None and message.robots:
            # both ends of every sensor topic use the assigned depth (the reader's window holds
            # the deepest writer's history)
            self.sensor_reader.retune(depth=max(q.depth for q in message.robots.values()))
        rates = ", ".join(
            f"{robot} {q.rate_hz:.2f} Hz D={q.depth}" for robot, q in message.robots.items()
        )
        if message.topics:  # per topic: each robot's range of rates
            rates = ", ".join(
                f"{robot} {min(q.rate_hz for q in own.values()):.2f}-"
                f"{max(q.rate_hz for q in own.values()):.2f} Hz over {len(own)} topics"
                for robot, own in message.topics.items()
                if own
            )
        self._event(
            f"QoS epoch {message.epoch} ({reason}): T_avg={message.t_avg:.3f}, {rates}", "INFO"
        )


def _started_ns(stats: RobotStats | None) -> int | None:
    """When the robot's incarnation started, on the CEDDP's clock (None: not said)."""
    if stats is None or not stats.started_ns:
        return None
    offset = stats.clock.offset_ns if stats.clock is not None else None
    return stats.started_ns + (offset or 0)


def _started_text(stats: RobotStats | None) -> str:
    started = _started_ns(stats)
    if started is None:
        return ""
    return f" (started {time.strftime('%H:%M:%S', time.gmtime(started / 1e9))} UTC)"
