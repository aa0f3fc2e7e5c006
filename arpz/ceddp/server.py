"""The CEDDP server: the fleet's Zenoh router, with ingest, planning, metrics and dashboard.

``CeddpServer`` wires the CEDDP's parts together and owns their life cycle and the summary; each
part is a module of its own. Threads: the sensor path (``intake``: the reliable channel's
Reader threads, or one raw ingest worker pulling a Zenoh FIFO) feeds ``Ingest`` (decode,
sequence check, cache control, planners); the control worker (``control``) keeps the fleet's
registry from the robots' reports and tokens and re-solves QoS; the metrics ticker (``metrics``)
builds the dashboard's frames and persists the summary; the downlink (``downlink``) writes to
the robots; the dashboard logs to Rerun on its own thread. All of them take the ingest lock to
touch shared state.
"""

from __future__ import annotations

import collections
import dataclasses
import json
import logging
import os
import threading
import time
from dataclasses import asdict
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec

from arpz.ceddp.cache_control import CacheControl
from arpz.ceddp.clock_service import ClockService, ClockWatch
from arpz.ceddp.control import KIND_NAMES, ControlWorker, RobotRecord
from arpz.ceddp.downlink import Downlink, DownlinkCounters
from arpz.ceddp.identity import identity_of
from arpz.ceddp.ingest import Ingest
from arpz.ceddp.intake import SensorIntake
from arpz.ceddp.metrics import MetricsTicker
from arpz.ceddp.mission import MissionRunner
from arpz.ceddp.pacing import Pacer
from arpz.ceddp.planner import (
    CostlyPlanner,
    HelloRelay,
    Planner,
    PlannerCommands,
    command_contract,
    make_planner,
)
from arpz.ceddp.qos_control import QosController
from arpz.ceddp.services import RobotServices, ServiceCaller, services_summary
from arpz.ceddp.status import StatusReader
from arpz.ceddp.summary import previous_run, qos_summary, resolve, robot_summary
from arpz.channel.io import Inlet, Outlet
from arpz.core import keys
from arpz.core.config import CeddpConfig, ConfigError
from arpz.core.frames import DashboardLike, Event, WorldMap, WorldView
from arpz.core.messages import encode, new_incarnation, writer_id
from arpz.core.msgtypes import MessageTypes
from arpz.core.transport import Handle, Transport
from arpz.mission.judge import MissionResult

if TYPE_CHECKING:  # imported when their port is set (docs/tools.md "Live views")
    from arpz.bridge.bridge import Bridge  # imported when [ros2] is enabled (docs/ros2.md)
    from arpz.ceddp.foxglove_live import FoxgloveLive
    from arpz.ceddp.web import StatusWeb

#: events kept for the summary (the dashboard and the log have every one)
MAX_EVENTS = 10_000
log = logging.getLogger(__name__)


def previous_summary_path(config: CeddpConfig) -> Path | None:
    """The file ``previous_summary`` names; "latest": the newest ``summary*.json`` next to
    ``summary_json`` (which, if it exists at start, is the previous run's)."""
    ref = config.previous_summary
    if not ref:
        return None
    if ref != "latest":
        return Path(ref)
    if not config.summary_json:
        return None
    here = Path(config.summary_json)
    found = sorted(here.parent.glob("summary*.json"), key=lambda p: p.stat().st_mtime)
    return found[-1] if found else None


def write_json_atomically(path: Path, doc: dict[str, Any]) -> None:
    """Write ``doc`` as indented JSON atomically: a reader, or a kill -9 mid-write, never sees
    half. msgspec's encoder and formatter, not ``json.dumps(indent=2)``: with an indent the
    standard library falls back to its pure-Python encoder (``python
    benchmarks/investigations/metrics_cost.py``: 22.8 against 3.9 ms for a 25-robot summary), every
    summary_period_s on the metrics thread. A float that is not finite is written as null
    (``json.dumps`` wrote NaN, which is not JSON)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    partial.write_bytes(msgspec.json.format(msgspec.json.encode(doc), indent=2))
    os.replace(partial, path)


class CeddpServer:
    """One CEDDP: ``start`` opens every key and starts the workers, ``run`` waits for a stop,
    ``shutdown`` drains, closes, and returns (and writes) the reconciled summary."""

    def __init__(
        self,
        config: CeddpConfig,
        transport: Transport,
        *,
        dashboard: DashboardLike | None = None,
        planner: Planner | None = None,
    ) -> None:
        """``planner``: one planner of the caller's beside the built-in ones and the config's
        ``[[planners]]`` (which run guarded: an exception in one is counted, not fatal)."""
        self.config = config
        self.transport = transport
        self.dashboard = dashboard
        self.incarnation = new_incarnation()
        #: the event log of the summary, newest MAX_EVENTS (a robot that rejoins in a loop must
        #: not grow the CEDDP's memory); the older ones are counted in events_dropped
        self.events: collections.deque[str] = collections.deque(maxlen=MAX_EVENTS)
        self.events_dropped = 0
        #: the message types of typed topics: the standard ones and ``msg_paths``' (as given:
        #: ``python -m arpz.ceddp`` makes them relative to the config's folder)
        self.types = MessageTypes()
        self.types.add_msg_paths(config.msg_paths)
        self.types.add_srv_paths(config.msg_paths)
        self.sink = Downlink(
            transport, config.fleet, config, max_per_robot=config.max_topics_per_robot
        )
        #: calls of the robots' services (docs/nodes.md "Services"), counted in the summary; made
        #: before the planners, which call through it (the registry and the metrics it asks are
        #: read at each call)
        self.services = ServiceCaller(
            transport,
            config.fleet,
            types=self.types,
            caller=writer_id("ceddp", self.incarnation),
            directory=self._robot_services,
            access_control=lambda: (
                self.metrics.identity.access_control if self.metrics.identity is not None else None
            ),
        )
        self.hello_relay = HelloRelay(
            self.sink, writer_id("ceddp", self.incarnation), relay=config.hello.relay
        )
        self.planners: list[Planner] = [self.hello_relay] + ([planner] if planner else [])
        #: the team's planners of ``[[planners]]`` (docs/nodes.md), each behind a guard
        commands = PlannerCommands(
            self.sink,
            writer_id("ceddp", self.incarnation),
            command_type=self._command_type,
            types=self.types,
        )
        self.team_planners = [
            make_planner(
                entry.cls,
                entry.options,
                commands,
                setting=f"planners[{i}]",
                on_first_fault=lambda text: self._event(text, "ERROR"),
                services=self.services,
            )
            for i, entry in enumerate(config.planners)
        ]
        self.planners.extend(self.team_planners)
        if config.overload.planner_cost_us > 0:
            self.planners.append(CostlyPlanner(config.overload.planner_cost_us))
        self.mission: MissionRunner | None = None
        if config.mission is not None:
            self.mission = MissionRunner(
                config.mission,
                self.sink,
                writer_id("ceddp", self.incarnation),
                self._event,
                on_result=self._on_mission_result,
                on_view=self._on_world_view,
                command_acks=lambda robot: self.sink.unacknowledged_s(robot, "velocity"),
            )
            self.planners.append(self.mission)
        self._fanout = _Fanout(self.planners)
        self.ingest = Ingest(
            config.fleet,
            self._fanout,
            CacheControl(enabled=config.cache_control),
            max_robots=config.max_robots,
            max_topics_per_robot=config.max_topics_per_robot,
            max_sample_bytes=config.max_sample_bytes,
            types=self.types,
        )
        self.qos = (
            QosController(config.qos, writer_id("ceddp", self.incarnation))
            if config.qos.enabled
            else None
        )
        #: robots' clock offsets (latency correction, the bound) and the clock they query
        self.clock = ClockWatch(config.clock, self.ingest, self._event)
        self.clock_service = ClockService(transport, config.fleet) if config.clock.serve else None
        self.control = ControlWorker(
            config,
            self.ingest,
            self.sink,
            self.planners,
            self.qos,
            self._event,
            clock=self.clock,
            command_contract=lambda: command_contract(self.incarnation, self.team_planners),
        )
        self.intake = SensorIntake(
            config, transport, self.ingest, self._fanout, self.control, self._event
        )
        self.metrics = MetricsTicker(
            config,
            self.ingest,
            self.control.robots,
            self.sink,
            self.planners,
            dashboard,
            refused=self._refused_by_robot,
            persist_partial=lambda: self._persist({**self.summary(), "complete": False}),
            sensor_path=lambda: (self.intake.processed, self.intake.idle_s()),
            backlog_ms=self.intake.take_backlog_ms,
            on_budget=self.control.on_budget,
            clock=self.clock,
            identity=identity_of(config),
        )
        #: the fleet's state for the live views (read-only, docs/tools.md "Live views")
        self.status = StatusReader(
            config,
            self.ingest,
            self.control.robots,
            lambda: self.metrics.last_frame,
            processed=lambda: self.intake.processed,
            channel=lambda: self.intake.reader.stats() if self.intake.reader else None,
            views_dropped=self._views_dropped,
        )
        self.foxglove: FoxgloveLive | None = None
        self.web: StatusWeb | None = None
        #: the ROS 2 bridge on this router's session ([ros2], docs/ros2.md)
        self.bridge: Bridge | None = None
        if config.ros2.enabled:
            from arpz.bridge.factory import bridge_class

            self.bridge = bridge_class(config.ros2)(
                transport,
                config.fleet,
                config,
                config.ros2,
                partition=config.partition,
                types=self.types,
                services=self.services,
            )
        self._reports: Inlet | None = None
        self._contract: Handle | None = None
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._started_ns = time.time_ns()

    @property
    def robots(self) -> dict[str, RobotRecord]:
        """The fleet's registry (kept by the control worker)."""
        return self.control.robots

    @property
    def processed(self) -> int:
        """Sensor samples taken by the ingest so far."""
        return self.intake.processed

    # -- life cycle ---------------------------------------------------------------------------

    def _load_previous_run(self) -> None:
        """Read ``previous_summary`` (a restart's predecessor); a missing or unreadable one is
        logged and ignored: it must never keep a restarting CEDDP from serving."""
        path = previous_summary_path(self.config)
        if path is None:
            return
        try:
            seen = previous_run(json.loads(path.read_text(encoding="utf-8")))
        except (OSError, ValueError) as exc:
            log.warning("previous summary %s not read: %s", path, exc)
            return
        self.ingest.load_previous_run(seen)
        self._event(f"previous run's summary {path}: {len(seen)} topics it had received")

    def _start_live_views(self) -> None:
        """The status page, Foxglove and the Rerun web viewer, each when its port is set
        (docs/tools.md "Live views"), before anything else starts: a port in use raises ConfigError
        naming its setting, and what was opened before it is closed again."""
        cfg = self.config
        try:
            if cfg.web_port:
                from arpz.ceddp.web import StatusWeb

                self.web = StatusWeb(self.status.read, host=cfg.live_host, port=cfg.web_port)
            if cfg.foxglove_port:
                from arpz.ceddp.foxglove_live import FoxgloveLive

                self.foxglove = FoxgloveLive(
                    host=cfg.live_host, port=cfg.foxglove_port, kind_of=self.status.kind_of
                )
            if cfg.rerun_web_port:  # last: Rerun's viewer cannot be stopped once it serves
                from arpz.ceddp.dashboard import serve_web_viewer

                serve_web_viewer(cfg.rerun_web_port)
                self._event(f"Rerun web viewer on http://0.0.0.0:{cfg.rerun_web_port}/")
        except ConfigError:
            if self.foxglove is not None:
                self.foxglove.stop()
            if self.web is not None:
                self.web.close()
            raise
        if self.foxglove is not None:
            self.planners.append(self.foxglove)  # fed like a planner, started and stopped so
            self.metrics.frame_listeners.append(self.foxglove.on_metrics)
            self._event(f"Foxglove on ws://{cfg.live_host}:{self.foxglove.port}")
        if self.web is not None:
            self.web.start()
            self._event(f"status page on http://{cfg.live_host}:{self.web.port}/ (and /metrics)")

    def _views_dropped(self) -> dict[str, int]:
        """Frames each live view dropped because it fell behind."""
        dropped = {"rerun": self.dashboard.dropped} if self.dashboard is not None else {}
        if self.foxglove is not None:
            dropped["foxglove"] = self.foxglove.dropped
        return dropped

    def start(self) -> None:
        cfg = self.config
        self._start_live_views()
        self._load_previous_run()
        fleet = cfg.fleet
        control = self.control
        if self.clock_service is not None:  # before the presence token: robots query at once
            self.clock_service.start()
        # what the team's planners send, for robots to check at start-up (docs/nodes.md)
        contract = encode(command_contract(self.incarnation, self.team_planners))
        self._contract = self.transport.serve(keys.ceddp_commands_key(fleet), lambda _: contract)
        self.intake.open()
        if self.bridge is not None:
            self.bridge.start()
        self._reports = Inlet(
            self.transport,
            keys.all_reports(fleet),
            cfg.profile("report"),
            control.on_report,
            on_incompatible=control.on_incompatible,
        )
        if self.qos is not None:  # one CEDDP of a mesh runs QoS control (docs/operations.md)
            control.qos_out = Outlet(
                self.transport, keys.ceddp_qos_key(fleet), cfg.profile("assignment", downlink=True)
            )
        self.metrics.stats_out = Outlet(
            self.transport, keys.ceddp_stats_key(fleet), cfg.profile("report")
        )
        self.transport.subscribe(keys.ceddp_qos_request_key(fleet), control.on_qos_request)
        self.transport.watch_liveliness(keys.all_presence(fleet), control.on_presence)
        self.transport.watch_liveliness(keys.all_robot_modes(fleet), control.on_mode)
        self.transport.declare_token(keys.ceddp_presence_key(fleet))
        self.transport.declare_token(keys.ceddp_mode_key(fleet, cfg.reliability))
        workers = [
            (control.run, "arpz-control"),
            (lambda: self.metrics.run(self._stop), "arpz-metrics"),
        ]
        if self.intake.raw is not None:
            workers.append((self.intake.run_raw, "arpz-ingest"))
        for target, name in workers:
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        self._fanout.refresh()
        for planner in self.planners:
            planner.start()
        if self.mission is not None and self.dashboard is not None:
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
        if self.web is not None:
            self.web.close()
        self._stop.set()
        self.intake.stop()
        if self.clock_service is not None:
            self.clock_service.close()
        if self._contract is not None:
            self._contract.undeclare()
        if self._reports is not None:
            self._reports.close()
        self.control.queue.close()
        for thread in self._threads:
            thread.join(timeout=10)
            if thread.is_alive():
                log.error("thread %s did not stop within 10 s", thread.name)
        self.metrics.tick()
        self._event("CEDDP stopping")
        if self.bridge is not None:
            self.bridge.close()
        self.sink.close()
        for outlet in (self.control.qos_out, self.metrics.stats_out):
            if outlet is not None:
                outlet.close(0.0)
        summary = self.summary()
        if self.dashboard is not None:
            self.dashboard.close()
            summary["dashboard"]["dropped"] = self.dashboard.dropped
            summary["dashboard"]["rows_refused"] = self.dashboard.rows_refused
        summary["complete"] = True
        self._persist(summary)
        return summary

    def _persist(self, summary: dict[str, Any]) -> None:
        if self.config.summary_json:
            write_json_atomically(Path(self.config.summary_json), summary)

    # -- events -------------------------------------------------------------------------------

    def _on_mission_result(self, result: MissionResult) -> None:
        # the line the demo (and a person at the console) waits for
        print(f"arpz.ceddp: mission {result.mission}: {result.reason}", flush=True)

    def _on_world_view(self, view: WorldView) -> None:
        if self.dashboard is not None:
            self.dashboard.submit(view)

    def _command_type(self, robot: str, name: str) -> str | None:
        """The ROS 2 type ``robot`` announced for its command ``name`` (None: a value)."""
        record = self.control.robots.get(robot)
        announce = record.announce if record is not None else None
        return announce.command_types.get(name) if announce is not None else None

    def _robot_services(self, robot: str) -> RobotServices:
        """What the registry knows of ``robot`` for a service call: present, and the services
        its latest announcement lists."""
        record = self.control.robots.get(robot)
        if record is None:
            return RobotServices(present=False)
        announce = record.announce
        return RobotServices(record.alive, announce.services if announce is not None else None)

    def _event(self, text: str, level: str = "INFO") -> None:
        log.log({"WARN": logging.WARNING, "ERROR": logging.ERROR}.get(level, logging.INFO), text)
        stamp = time.time_ns()
        if len(self.events) == self.events.maxlen:
            self.events_dropped += 1
        self.events.append(f"{stamp}: {text}")
        if self.dashboard is not None:
            self.dashboard.submit(Event(stamp, text, level))

    # -- summary ------------------------------------------------------------------------------

    def _refused_by_robot(self) -> dict[str, dict[str, int]]:
        """Samples refused because the robot's mode disagrees with ours, per robot and key."""
        per_key: dict[str, int] = dict(self.intake.refused())
        if self._reports is not None:
            per_key.update(self._reports.refused)
        out: dict[str, dict[str, int]] = {}
        for key, count in per_key.items():
            parsed = keys.parse_robot_key(key)
            if parsed is not None:
                out.setdefault(parsed[0], {})["/".join(key.split("/")[4:])] = count
        return out

    def summary(self) -> dict[str, Any]:
        """Per robot and topic: what the robot says it did and what arrived here, reconciled."""
        refused = self._refused_by_robot()
        queue = self.control.queue
        reader = self.intake.reader
        reader_stats = msgspec.to_builtins(reader.stats()) if reader is not None else None
        frames = self.intake.frames
        # camera frames and point clouds: what reassembly delivered and dropped (incomplete when
        # a newer frame won, over a bound), and the fragment channel's own counters
        frames_stats = msgspec.to_builtins(frames.stats()) if frames is not None else None
        downlink: dict[str, dict[str, DownlinkCounters]] = {}
        for (robot, name), counters in self.sink.snapshot().items():
            downlink.setdefault(robot, {})[name] = counters
        with self.ingest.lock:
            names = sorted({r for r, _ in self.ingest.topics} | set(self.control.robots))
        robots = {}
        pace = Pacer()  # 50 robots' rows take tens of ms: the sensor path goes first
        for robot in names:
            pace()
            # the lock per robot, not for the whole fleet: a robot's counts stay consistent
            # with each other; its percentiles are computed once the lock is released
            with self.ingest.lock:
                report = self.control.robots.get(robot, RobotRecord()).as_report()
                report.refused.update(refused.get(robot, {}))
                report.downlink.update(downlink.get(robot, {}))
                report = dataclasses.replace(report, clock=self.clock.summary(robot))
                row = robot_summary(self.ingest, robot, report, defer=True)
            robots[robot] = resolve(row)
        return {
            "fleet": self.config.fleet,
            "partition": self.config.partition,
            "duration_s": round((time.time_ns() - self._started_ns) / 1e9, 3),
            "robots": robots,
            "hello_relay": asdict(self.hello_relay.counters),
            "ingest": {
                "processed": self.intake.processed,
                "path": "reliable channel" if self.config.channel else "raw",
                "channel_lost": self.intake.channel_lost,
                # the longest a sample waited before the sensor path took it (None: raw path)
                "backlog_ms_max": self.intake.worst_backlog_ms(),
                # the same wait's p50 and p99 over the pulls that found samples waiting: a p99
                # latency far above them is spent before the router took the sample in
                **dict(
                    zip(
                        ("backlog_ms_p50", "backlog_ms_p99"),
                        self.intake.backlog_ms_quantiles(50, 99),
                        strict=True,
                    )
                ),
                # each sample's time inside the CEDDP, router to processed (upper bounds): a
                # p99 latency above it is spent on the robots, the link or the router's threads
                **self.intake.sojourn_ms(),
                "channel": reader_stats,
                "frames": frames_stats,
                "unknown_keys": self.ingest.counters.unknown_keys,
                "over_limit": self.ingest.counters.over_limit,
                "unknown_control_keys": self.control.counters.unknown_control_keys,
                "commands_over_limit": dict(self.sink.over_limit),
                "control": {
                    "coalesced": queue.coalesced,
                    "dropped": {KIND_NAMES[k]: n for k, n in queue.dropped.items()},
                    "peak": queue.peak,
                    "reports_oversize": self.control.counters.reports_oversize,
                    "reports_over_limit": self.control.counters.reports_over_limit,
                },
            },
            "dashboard": {"rrd": self.config.rrd, "dropped": 0, "rows_refused": 0},
            "foxglove": self.foxglove.counters() if self.foxglove is not None else None,
            "qos": qos_summary(self.qos) if self.qos is not None else None,
            "overload": self.metrics.governor.summary(),
            "clock": {
                **self.clock.fleet_summary(),
                "served": self.clock_service is not None,
                "requests_answered": self.clock_service.answered if self.clock_service else 0,
                "bad_requests": self.clock_service.bad_requests if self.clock_service else 0,
            },
            "mission": self.mission.summary() if self.mission is not None else None,
            "ros2": self.bridge.stats() if self.bridge is not None else None,
            "planners": {p.name: p.faults() for p in self.team_planners},
            "services": services_summary(
                self.services.counters(),
                {
                    robot: record.stats.services
                    for robot, record in list(self.control.robots.items())
                    if record.stats is not None
                },
            ),
            "events": list(self.events),
            "events_dropped": self.events_dropped,
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
