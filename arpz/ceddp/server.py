"""The CEDDP server: the fleet's Zenoh router, with ingest, planning, metrics and dashboard.

Threads: sensor samples wait in a Zenoh-owned FIFO of ``ingest_queue_limit`` samples (no Python
callback per sample, which measured faster than even a bare counting callback); when it is full
Zenoh stops reading the link and the robots' publishers (congestion control BLOCK) wait, so a
slow CEDDP delays samples but never drops them. One worker pulls them in batches through
``Ingest`` (decode, sequence check, cache control, planner); "arrival" is when the worker takes
the sample, so the latency figure includes any wait in the CEDDP. Reports and presence arrive by
callback on a second, low-rate queue and worker. One ticker turns the counters into a
``MetricsFrame`` every ``metrics_period_s`` for the dashboard and publishes ``CeddpStats``. The
dashboard logs to Rerun on its own thread.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Protocol

import msgspec

from arpz import keys
from arpz.ceddp.cache_control import CacheControl
from arpz.ceddp.ingest import Ingest
from arpz.ceddp.mission import MissionRunner, WorldView
from arpz.ceddp.planner import HelloRelay, Planner
from arpz.ceddp.qos_control import QosController
from arpz.ceddp.summary import RobotReport, qos_summary, robot_summary
from arpz.config import CeddpConfig
from arpz.messages import (
    ANNOUNCE_DECODER,
    DECODE_ERRORS,
    QOS_ACK_DECODER,
    STATS_DECODER,
    TELEMETRY_DECODER,
    Announce,
    CeddpStats,
    RobotStats,
    TopicRate,
    encode,
    new_incarnation,
    writer_id,
)
from arpz.percentiles import percentile
from arpz.reliability import (
    DataInfo,
    MessageLostStatus,
    Reader,
    ReaderEventCallbacks,
    UnchangedStatus,
)
from arpz.sim.judge import MissionResult
from arpz.transport import PullSubscriber, Transport

log = logging.getLogger(__name__)

_CONTROL, _PRESENCE, _QOS_REQUEST = 1, 2, 3
_CONTROL_KINDS = ("stats", "announce", "qos", "telemetry")


class DashboardLike(Protocol):
    dropped: int

    def submit(self, item: Any) -> bool: ...
    def close(self) -> None: ...


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

    def as_report(self) -> RobotReport:
        return RobotReport(
            alive=self.alive,
            joins=self.joins,
            leaves=self.leaves,
            control_decode_errors=self.control_decode_errors,
            stats=self.stats,
        )


@dataclass
class ServerCounters:
    unknown_control_keys: int = 0
    #: samples the reliable channel reported irrecoverably lost (GAP, timeout, writer gone)
    channel_lost: int = 0
    events: list[str] = field(default_factory=list)


class _TransportSink:
    def __init__(self, transport: Transport, fleet: str) -> None:
        self._transport = transport
        self._fleet = fleet

    def send(self, robot: str, name: str, payload: bytes) -> None:
        self._transport.put(keys.command_key(self._fleet, robot, name), payload)


class CeddpServer:
    def __init__(
        self,
        config: CeddpConfig,
        transport: Transport,
        *,
        dashboard: DashboardLike | None = None,
        planner: Planner | None = None,
    ) -> None:
        self.config = config
        self.transport = transport
        self.dashboard = dashboard
        self.incarnation = new_incarnation()
        self.sink = _TransportSink(transport, config.fleet)
        self.hello_relay = HelloRelay(
            self.sink, writer_id("ceddp", self.incarnation), relay=config.hello.relay
        )
        self.planners: list[Planner] = [self.hello_relay] + ([planner] if planner else [])
        self.mission: MissionRunner | None = None
        if config.mission is not None:
            self.mission = MissionRunner(
                config.mission,
                self.sink,
                writer_id("ceddp", self.incarnation),
                self._event,
                on_result=self._on_mission_result,
                on_view=self._on_world_view,
            )
            self.planners.append(self.mission)
        self._fanout = _Fanout(self.planners)
        self.ingest = Ingest(
            config.fleet,
            self._fanout,
            CacheControl(enabled=config.cache_control),
            max_robots=config.max_robots,
            max_topics_per_robot=config.max_topics_per_robot,
        )
        self.robots: dict[str, RobotRecord] = {}
        self.qos = (
            QosController(config.qos, writer_id("ceddp", self.incarnation))
            if config.qos.enabled
            else None
        )
        self.counters = ServerCounters()
        self._control: queue.SimpleQueue[tuple[int, str, bytes] | None] = queue.SimpleQueue()
        self._sensors: PullSubscriber | None = None
        self._reader: Reader | None = None
        self._wake_key = keys.sensor_key(config.fleet, "ceddp-wake", "wake")
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._started_ns = time.time_ns()
        self._last_tick: tuple[float, float, dict[tuple[str, str], tuple[int, int]]] = (
            time.monotonic(),
            time.process_time(),
            {},
        )
        self.processed = 0

    # -- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        fleet = self.config.fleet
        control = self._control

        def on_control(key: str, payload: bytes, _att: bytes | None) -> None:
            control.put((_CONTROL, key, payload))

        def on_presence(key: str, alive: bool) -> None:
            control.put((_PRESENCE, key, b"\x01" if alive else b""))

        if self.config.sensor_qos is None:
            self._sensors = self.transport.subscribe_pull(
                keys.all_sensors(fleet, self.config.partition), self.config.ingest_queue_limit
            )
        else:
            self._reader = Reader(
                self.transport,
                keys.all_sensors(fleet, self.config.partition),
                self.config.sensor_qos,
                self._on_channel_data,
                events=ReaderEventCallbacks(
                    message_lost=self._on_channel_lost,
                    unchanged=self._on_channel_unchanged,
                    incompatible_qos=lambda status: self._event(
                        f"reliable channel: incompatible QoS ({status.last_policy_kind}) "
                        f"with {status.peer}",
                        level="ERROR",
                    ),
                ),
            )
        self.transport.subscribe(f"{keys.fleet_prefix(fleet)}/robot/*/*", on_control)
        self.transport.subscribe(
            keys.ceddp_qos_request_key(fleet),
            lambda key, payload, _att: control.put((_QOS_REQUEST, key, payload)),
        )
        self.transport.watch_liveliness(keys.all_presence(fleet), on_presence)
        self.transport.declare_token(keys.ceddp_presence_key(fleet))
        workers = [(self._work_control, "arpz-control"), (self._tick_loop, "arpz-metrics")]
        if self._sensors is not None:
            workers.append((self._work_sensors, "arpz-ingest"))
        for target, name in workers:
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        self._fanout.refresh()
        for planner in self.planners:
            planner.start()
        if self.mission is not None and self.dashboard is not None:
            from arpz.ceddp.dashboard import WorldMap

            world = self.mission.world
            self.dashboard.submit(
                WorldMap(
                    time.time_ns(),
                    walls=[[(float(x), float(y)) for x, y in strip] for strip in world.wall_strips],
                    obstacles=[
                        [(float(x), float(y)) for x, y in o.corners()] for o in world.obstacles
                    ],
                )
            )
        self._event(
            f"CEDDP {self.incarnation} serving fleet '{fleet}' on {', '.join(self.config.listen)}"
        )

    def run(self, stop: threading.Event) -> None:
        end = time.monotonic() + (self.config.duration_s or float("inf"))
        while not stop.is_set() and time.monotonic() < end:
            stop.wait(min(0.2, max(end - time.monotonic(), 0.0)))

    def shutdown(self) -> dict[str, Any]:
        """Process what is queued, log a last frame, close the dashboard, write the summary."""
        for planner in self.planners:
            planner.stop()
        self._stop.set()
        if self._sensors is not None:
            # wake the ingest worker: this sample queues behind everything already received
            self.transport.put(self._wake_key, b"")
        if self._reader is not None:
            self._reader.close()
        self._control.put(None)
        for thread in self._threads:
            thread.join(timeout=10)
            if thread.is_alive():
                log.error("thread %s did not stop within 10 s", thread.name)
        self._tick()
        self._event("CEDDP stopping")
        summary = self.summary()
        if self.dashboard is not None:
            self.dashboard.close()
            summary["dashboard"]["dropped"] = self.dashboard.dropped
        if self.config.summary_json:
            path = Path(self.config.summary_json)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(summary, indent=2), encoding="utf-8")
        return summary

    # -- workers ------------------------------------------------------------------------------

    def _work_sensors(self) -> None:
        """Pull sensor samples in batches; block in ``recv`` (no GIL held) when there are none."""
        sensors, ingest, stop, wake = self._sensors, self.ingest, self._stop, self._wake_key
        assert sensors is not None, "start() declares the subscriber before the worker runs"
        try_recv = sensors.try_recv
        while True:
            item = try_recv()
            if item is None:
                item = sensors.recv()
            batch = [item]
            while len(batch) < 2000 and (item := try_recv()) is not None:
                batch.append(item)
            arrival_ns = time.time_ns()
            with ingest.lock:
                for key, payload, _att in batch:
                    if key == wake and stop.is_set():
                        return
                    try:
                        ingest.handle_sensor(key, payload, arrival_ns)
                    except Exception:  # a bad sample or a planner bug must not stop the CEDDP
                        log.exception("ingest failed on %s", key)
                self.processed += len(batch)

    def _on_channel_data(self, payload: bytes, info: DataInfo) -> None:
        """A sample delivered by the reliable channel (in order per writer, on its worker)."""
        with self.ingest.lock:
            try:
                self.ingest.handle_sensor(info.key, payload, time.time_ns())
            except Exception:
                log.exception("ingest failed on %s", info.key)
            self.processed += 1

    def _on_channel_unchanged(self, status: UnchangedStatus) -> None:
        """A robot's local cache held a repeat back: planners judging freshness must know."""
        if not self._fanout.wants_unchanged:
            return
        parsed = keys.parse_robot_key(status.key)
        if parsed is not None and parsed[1] == "sensor":
            self._fanout.on_unchanged(parsed[0], parsed[2], status.stamp_ns)

    def _on_channel_lost(self, status: MessageLostStatus) -> None:
        self.counters.channel_lost += status.total_count_change

    def _work_control(self) -> None:
        while (item := self._control.get()) is not None:
            kind, key, payload = item
            with self.ingest.lock:
                try:
                    if kind == _CONTROL:
                        self._handle_control(key, payload)
                    elif kind == _PRESENCE:
                        self._handle_presence(key, bool(payload))
                    else:
                        self._reassign_qos("requested", force=True)
                except Exception:
                    log.exception("control message failed on %s", key)

    def _handle_control(self, key: str, payload: bytes) -> None:
        parsed = keys.parse_robot_key(key)
        if parsed is None or parsed[1] not in _CONTROL_KINDS or parsed[2]:
            self.counters.unknown_control_keys += 1
            return
        robot, kind, _ = parsed
        record = self.robots.setdefault(robot, RobotRecord())
        try:
            if kind == "stats":
                stats = STATS_DECODER.decode(payload)
                if record.stats is None or not record.stats.final or stats.final:
                    record.stats = stats
            elif kind == "announce":
                record.announce = ANNOUNCE_DECODER.decode(payload)
                count = len(record.announce.sensors) + len(record.announce.commands)
                if count != record.topic_count:
                    record.topic_count = count
                    self._reassign_qos(f"robot {robot} uses {count} topics")
            elif kind == "telemetry":
                telemetry = TELEMETRY_DECODER.decode(payload)
                for planner in self.planners:
                    planner.on_telemetry(robot, telemetry)
            elif self.qos is not None:
                self._event(self.qos.on_ack(QOS_ACK_DECODER.decode(payload)))
        except DECODE_ERRORS as exc:
            record.control_decode_errors += 1
            log.warning("undecodable %s report from %s: %s", kind, robot, exc)

    def _handle_presence(self, key: str, alive: bool) -> None:
        parsed = keys.parse_robot_key(key)
        if parsed is None:
            return
        robot = parsed[0]
        record = self.robots.setdefault(robot, RobotRecord())
        if record.alive == alive:
            return
        record.alive = alive
        if alive:
            record.joins += 1
        else:
            record.leaves += 1
        self._event(
            f"robot {robot} {'joined' if alive else 'left'}", level="INFO" if alive else "WARN"
        )
        if not alive:
            self.ingest.cache_control.forget(robot)
            if record.topic_count is not None:
                record.topic_count = None
                self._reassign_qos(f"robot {robot} left")
        elif record.topic_count is not None:
            # its announcement came first (reports and presence travel separately)
            self._reassign_qos(f"robot {robot} joined with {record.topic_count} topics")
        for planner in self.planners:
            planner.on_robot(robot, alive)

    def _on_mission_result(self, result: MissionResult) -> None:
        # the line the demo (and a person at the console) waits for
        print(f"arpz.ceddp: mission {result.mission}: {result.reason}", flush=True)

    def _on_world_view(self, view: WorldView) -> None:
        if self.dashboard is not None:
            self.dashboard.submit(view)

    def _reassign_qos(self, reason: str, *, force: bool = False) -> None:
        """Re-solve problem (6) for the robots present now; publish if the answer changed."""
        if self.qos is None:
            return
        topics = {
            robot: record.topic_count
            for robot, record in self.robots.items()
            if record.alive and record.topic_count is not None
        }
        before = len(self.qos.errors)
        message = self.qos.update(topics, reason, force=force)
        if message is None:
            if len(self.qos.errors) > before:
                self._event(self.qos.errors[-1], level="ERROR")
            return
        self.transport.put(keys.ceddp_qos_key(self.config.fleet), encode(message))
        rates = ", ".join(
            f"{robot} {q.rate_hz:.2f} Hz D={q.depth}" for robot, q in message.robots.items()
        )
        self._event(f"QoS epoch {message.epoch} ({reason}): T_avg={message.t_avg:.3f}, {rates}")

    # -- metrics ------------------------------------------------------------------------------

    def _tick_loop(self) -> None:
        while not self._stop.wait(self.config.metrics_period_s):
            try:
                self._tick()
            except Exception:
                log.exception("metrics tick failed")

    def _tick(self) -> None:
        now, cpu = time.monotonic(), time.process_time()
        last_now, last_cpu, last_counts = self._last_tick
        interval_s = max(now - last_now, 1e-6)
        frame_topics: dict[tuple[str, str], dict[str, float]] = {}
        rates: list[TopicRate] = []
        counts: dict[tuple[str, str], tuple[int, int]] = {}
        with self.ingest.lock:
            for slot, m in self.ingest.topics.items():
                received0, bytes0 = last_counts.get(slot, (0, 0))
                counts[slot] = (m.received, m.bytes)
                window = m.latency_ms.take_window()
                row = {
                    "rate_hz": (m.received - received0) / interval_s,
                    "bytes_per_s": (m.bytes - bytes0) / interval_s,
                    "lost": float(m.lost),
                    "cc_discarded": float(self.ingest.cache_counters(*slot).hits),
                    "decode_errors": float(m.decode_errors),
                }
                if window:
                    row["latency_ms_p50"] = percentile(window, 50) or 0.0
                    row["latency_ms_p99"] = percentile(window, 99) or 0.0
                stats = self.robots.get(slot[0], RobotRecord()).stats
                if stats is not None and slot[1] in stats.topics:
                    row["held_back"] = float(stats.topics[slot[1]].held_back)
                frame_topics[slot] = row
                rates.append(
                    TopicRate(
                        robot=slot[0],
                        topic=slot[1],
                        rate_hz=row["rate_hz"],
                        bytes_per_s=row["bytes_per_s"],
                    )
                )
            robots: dict[str, dict[str, float]] = {}
            for robot, record in self.robots.items():
                if record.stats is None:
                    continue
                row = {"cpu_percent": record.stats.cpu_percent}
                if record.stats.qos_rate_hz is not None:
                    row["qos_rate_hz"] = record.stats.qos_rate_hz
                if record.stats.qos_depth is not None:
                    row["qos_depth"] = float(record.stats.qos_depth)
                hello = record.stats.hello
                if hello is not None and hello.rtt_ms_p50 is not None:
                    row["hello_rtt_ms_p50"] = hello.rtt_ms_p50
                robots[robot] = row
        self._last_tick = (now, cpu, counts)
        cpu_percent = 100.0 * (cpu - last_cpu) / interval_s
        if self.dashboard is not None:
            from arpz.ceddp.dashboard import MetricsFrame

            robots.setdefault("ceddp", {})["cpu_percent"] = cpu_percent
            self.dashboard.submit(MetricsFrame(time.time_ns(), frame_topics, robots))
        try:
            self.transport.put(
                keys.ceddp_stats_key(self.config.fleet),
                encode(
                    CeddpStats(
                        stamp_ns=time.time_ns(), cpu_percent=round(cpu_percent, 2), topics=rates
                    )
                ),
            )
        except Exception as exc:  # the session may be closing
            log.debug("could not publish CEDDP stats: %s", exc)
        for planner in self.planners:
            planner.tick(now)

    def _event(self, text: str, level: str = "INFO") -> None:
        log.log({"WARN": logging.WARNING, "ERROR": logging.ERROR}.get(level, logging.INFO), text)
        stamp = time.time_ns()
        self.counters.events.append(f"{stamp}: {text}")
        if self.dashboard is not None:
            from arpz.ceddp.dashboard import Event

            self.dashboard.submit(Event(stamp, text, level))

    # -- summary ------------------------------------------------------------------------------

    def summary(self) -> dict[str, Any]:
        """Per robot and topic: what the robot says it did and what arrived here, reconciled."""
        with self.ingest.lock:
            names = sorted({r for r, _ in self.ingest.topics} | set(self.robots))
            robots = {
                robot: robot_summary(
                    self.ingest, robot, self.robots.get(robot, RobotRecord()).as_report()
                )
                for robot in names
            }
        return {
            "fleet": self.config.fleet,
            "partition": self.config.partition,
            "duration_s": round((time.time_ns() - self._started_ns) / 1e9, 3),
            "robots": robots,
            "hello_relay": asdict(self.hello_relay.counters),
            "ingest": {
                "processed": self.processed,
                "path": "raw" if self.config.sensor_qos is None else "reliable channel",
                "channel_lost": self.counters.channel_lost,
                "channel": msgspec.to_builtins(self._reader.stats()) if self._reader else None,
                "unknown_keys": self.ingest.counters.unknown_keys,
                "over_limit": self.ingest.counters.over_limit,
                "unknown_control_keys": self.counters.unknown_control_keys,
            },
            "dashboard": {"rrd": self.config.rrd, "dropped": 0},
            "qos": qos_summary(self.qos) if self.qos is not None else None,
            "mission": self.mission.summary() if self.mission is not None else None,
            "events": self.counters.events,
        }


class _Fanout(Planner):
    """Hands every planner callback to each planner in turn."""

    def __init__(self, planners: list[Planner]) -> None:
        self.planners = planners

    def refresh(self) -> None:
        """Ask for unchanged readings only if some planner wants them (they are most samples)."""
        self.wants_unchanged = any(p.wants_unchanged for p in self.planners)

    def on_unchanged(self, robot: str, topic: str, stamp_ns: int) -> None:
        for planner in self.planners:
            if planner.wants_unchanged:
                planner.on_unchanged(robot, topic, stamp_ns)

    def on_reading(self, reading: Any) -> None:
        for planner in self.planners:
            planner.on_reading(reading)

    def on_hello(self, robot: str, hello: Any) -> None:
        for planner in self.planners:
            planner.on_hello(robot, hello)
