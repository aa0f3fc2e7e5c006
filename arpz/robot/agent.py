"""The robot agent: the coordinator of one robot's parts.

``RobotAgent`` wires together what ``arpz.robot`` does, each part in a module of its own: the
sensors through the local cache to their channel writers (``sensing``), every periodic job on one
scheduler thread (``scheduler``), the CEDDP's commands, Hello hops and QoS assignment on one
command worker (``commands``), the Hello probe (``hello``), and the command watchdog
(``watchdog``). What it keeps itself: the reports (stats, announcements, QoS acks, telemetry),
applying a QoS assignment, and the life cycle (start, run, shutdown).
"""

from __future__ import annotations

import functools
import logging
import socket
import threading
import time
from pathlib import Path

import msgspec

from arpz.channel import QosPolicyKind
from arpz.channel.bundling import Bundler
from arpz.channel.io import FrameOutlet, Outlet, drain
from arpz.core import keys
from arpz.core.config import RobotConfig
from arpz.core.endpoints import endpoint_address, frame_fragment_bytes
from arpz.core.errors import ArpzError
from arpz.core.messages import (
    ANNOUNCE_DECODER,
    DECODE_ERRORS,
    STATS_DECODER,
    Announce,
    ClockStats,
    InboundCounters,
    QosAck,
    QosAssignmentMsg,
    RobotQos,
    RobotStats,
    Telemetry,
    TopicCounters,
    TopicInfo,
    encode,
    new_incarnation,
    writer_id,
)
from arpz.core.transport import Reopenable, Transport
from arpz.core.version import arpz_version, zenoh_version
from arpz.robot.actuation import Actuator, RecordingActuator
from arpz.robot.clock_sync import ClockSync
from arpz.robot.commands import CommandWorker
from arpz.robot.configuration import ConfigurationHandler, robot_computations
from arpz.robot.hello import HelloProbe
from arpz.robot.link_monitor import LinkWatch, Signals, Waiting, route_sources
from arpz.robot.process_cpu import PROCESS_CPU, cpu_percent
from arpz.robot.qos import decide
from arpz.robot.scheduler import Job, Scheduler
from arpz.robot.sensing import (
    SensorChannel,
    build_sensors,
    effective_sensors,
    message_types,
    sense,
)
from arpz.robot.sensors import value_type_of
from arpz.robot.services import ServiceHost, robot_service_types
from arpz.robot.sim_host import SimActuator, SimHost
from arpz.robot.watchdog import CommandWatchdog

log = logging.getLogger(__name__)

__all__ = ["DuplicateRobotError", "RobotAgent", "check_robot_id_free", "effective_sensors"]

#: how long the robot waits for the CEDDP to acknowledge its final report before closing
_FINAL_REPORT_WAIT_S = 2.0
#: the longest a stopping robot waits for a CEDDP that keeps acknowledging its sensor samples
_DRAIN_LIMIT_S = 30.0
#: the watchdog's default for a simulated body's motion commands (the mission sends at 20 Hz)
_SIM_VELOCITY_DEADLINE_S = 0.5


class RobotAgent:
    """One robot: its sensors through the local cache to the CEDDP, the CEDDP's commands and QoS
    assignment to its actuators, presence and self-reporting.

    Every key in both directions goes through an ``Outlet`` / ``Inlet`` with the profile the
    config declares for its kind of traffic (arpz/core/traffic.py): sensors and the Hello hops up,
    reports (stats, announcements, QoS acks, telemetry) up, commands, Hello hops and the QoS
    assignment down; with ``reliability = "none"`` all of them are plain Zenoh.

    Threads: ``run`` is the scheduler thread (sensors, Hello, simulated body, telemetry,
    watchdog, stats, announcements); the command worker applies commands and assignments; the
    channel's own threads only queue.
    """

    def __init__(
        self,
        config: RobotConfig,
        transport: Transport,
        *,
        actuator: Actuator | None = None,
        base_dir: Path | None = None,
    ) -> None:
        self.config = config
        self.transport = transport
        base_dir = base_dir or Path.cwd()
        self.sim: SimHost | None = None
        if config.sim is not None:
            self.sim = SimHost(config.sim, config.robot_id, seed=config.seed, base_dir=base_dir)
        self.actuator = actuator or (SimActuator(self.sim) if self.sim else RecordingActuator())
        self.incarnation = new_incarnation()
        self.writer = writer_id(config.robot_id, self.incarnation)
        fleet, robot = config.fleet, config.robot_id
        #: the clock against the CEDDP's, and the wall clock every stamp of this robot reads
        self.clock_sync = ClockSync(config.clock, transport, fleet)
        self._wall_ns = self.clock_sync.wall_ns
        #: the robot's wall clock at this incarnation's start (``RobotStats.started_ns``)
        self.started_ns = self._wall_ns()
        self._versions = (arpz_version(), zenoh_version())
        self.hello_probe = HelloProbe(
            robot,
            self.writer,
            Outlet(transport, keys.sensor_key(fleet, robot, keys.HELLO), config.profile("hello")),
            config.hello.timeout_s,
        )
        self.hello_probe.wall_ns = self._wall_ns
        #: the Hello round trips this robot originated
        self.hello = self.hello_probe.tracker
        report_qos = config.profile("report")
        self._stats_out = Outlet(transport, keys.stats_key(fleet, robot), report_qos)
        self._announce_out = Outlet(transport, keys.announce_key(fleet, robot), report_qos)
        self._ack_out = Outlet(transport, keys.qos_ack_key(fleet, robot), report_qos)
        self._telemetry_out: Outlet | None = None
        if config.sim is not None:
            self._telemetry_out = Outlet(transport, keys.telemetry_key(fleet, robot), report_qos)
        self._start_s = time.monotonic()
        self._last_cpu = PROCESS_CPU.read()
        self._cpu_percent = 0.0
        self._last_report_s = time.monotonic()
        self._telemetry_seq = 0
        #: the sensor messages of one scheduler tick as one Zenoh message (channel mode only: a
        #: bundle the link refuses is recovered by the writers' NACKs, not so a plain put)
        self.bundler: Bundler | None = None
        sensor_transport: Transport = transport
        if config.bundle_sensors and config.profile("sensor") is not None:
            self.bundler = Bundler(
                transport,
                max_bytes=config.frame_fragment_bytes or frame_fragment_bytes(config.connect),
            )
            sensor_transport = self.bundler
        #: the message types of the typed sensors (None: scalar sensors only)
        self.types = message_types(config, base_dir)
        self.sensors: list[SensorChannel] = build_sensors(
            config, sensor_transport, self.sim, base_dir, self.types
        )
        for sensor in self.sensors:
            sensor.wall_ns = self._wall_ns
        #: each typed sensor's RIHS01 type hash, for its announcement
        self._type_hashes = {
            s.config.name: self.types.type_hash(s.config.type)
            for s in self.sensors
            if self.types is not None and s.config.type is not None
        }
        #: the services this robot serves (``[[services]]``, arpz/robot/services.py)
        self.services = ServiceHost(
            config, transport, robot_service_types(config, base_dir, self.types)
        )
        #: the commands this robot acts on (the Hello hop is handled by the agent itself)
        self.command_names: list[str] = list(self.actuator.commands)
        self.watchdog = CommandWatchdog(self._watchdog_deadlines())
        self.commands = CommandWorker(
            config,
            transport,
            self.actuator,
            self.watchdog,
            clock=self._now_s,
            on_assignment=self._on_qos,
            on_hello=self.hello_probe.on_hop,
            on_incompatible=self._on_incompatible,
        )
        #: INCOMPATIBLE_QOS seen here, "what: why" (reported in stats)
        self.incompatible: list[str] = []
        #: the QoS the CEDDP assigned and this robot applied (None: running its own config)
        self.qos: RobotQos | None = None
        self.qos_epoch = 0
        self.qos_refused = 0
        #: each sensor with its scheduler job (a QoS assignment changes the job's period)
        self._sensor_jobs: list[tuple[SensorChannel, Job]] = []
        self.scheduler = self._make_scheduler()
        #: a configurator's solution (seed 002) applied live: arpz/robot/configuration.py
        sim = self.sim
        self.configuration = ConfigurationHandler(
            self.config,
            self.transport,
            incarnation=self.incarnation,
            sensor_jobs=self._sensor_jobs,
            computations=robot_computations(
                (lambda: sim.ranges) if sim is not None else None, self.actuator.safe_stop
            ),
            wall_ns=self.clock_sync.wall_ns,
            on_applied=lambda: self._publish_announce(0.0),
        )
        self._started = False
        #: the final report (``shutdown``) and whether the CEDDP acknowledged it
        self.final_stats: RobotStats | None = None
        self.final_acknowledged: bool | None = None
        #: the CEDDP's presence token (``watch_link``): alive now (None: not seen yet)
        self._ceddp_present: bool | None = None
        self._waiting = Waiting()

    def _now_s(self) -> float:
        return time.monotonic() - self._start_s

    def _watchdog_deadlines(self) -> dict[str, float]:
        watchdog = self.config.watchdog
        if not watchdog.enabled:
            return {}
        if watchdog.deadlines_s is not None:
            return dict(watchdog.deadlines_s)
        return {"velocity": _SIM_VELOCITY_DEADLINE_S} if self.sim is not None else {}

    # -- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        """Open the downlink (commands, Hello hops, QoS assignment), declare presence and mode,
        wait (bounded) for the CEDDP's readers, announce; sensing starts in ``run``."""
        cfg = self.config
        self.commands.start(self.command_names)
        self.configuration.start()
        self.services.start()
        self.transport.declare_token(keys.presence_key(cfg.fleet, cfg.robot_id))
        self.transport.declare_token(keys.robot_mode_key(cfg.fleet, cfg.robot_id, cfg.reliability))
        self.transport.watch_liveliness(keys.all_ceddp_modes(cfg.fleet), self._on_ceddp_mode)
        self._wait_for_readers(cfg.match_timeout_s)
        if cfg.clock.enabled and not self.clock_sync.first_estimate(cfg.clock.timeout_s):
            log.warning(
                "no reply to the clock request within %.1f s (is the CEDDP running, and does it "
                "serve %s?): latencies stay uncorrected until one comes",
                cfg.clock.timeout_s,
                keys.ceddp_clock_key(cfg.fleet),
            )
        self._publish_announce(0.0)
        self.commands.wait_for_writers(cfg.match_timeout_s)
        self._started = True
        log.info(
            "robot %s (%s) started with %d sensors (mode %s)",
            cfg.robot_id,
            self.incarnation,
            len(self.sensors),
            cfg.reliability,
        )

    def settle_clock(self, timeout_s: float) -> bool:
        """Take the clock estimate again now, and report it to the CEDDP at once; whether the
        burst's replies all came. For a load generator that started its robots together
        (``python -m arpz.perf fleet``): their first exchanges queued behind everyone's
        start-up, and an exchange with a 55 ms round trip may be 27 ms off, which the CEDDP
        took out of the robot's latencies until a better exchange reached it in a report (for
        0.5-1.5 s at 50 robots: the worst robots' p99 of a 60 s run; issue 17, stop 39). A
        robot started alone does not need it: its next bursts correct a poor first one."""
        if not self.config.clock.enabled or not self._started or not self.clock_sync.replies:
            return False  # no clock service answered at start: none to wait for
        settled = self.clock_sync.settle(timeout_s)
        self._publish_stats(final=False)
        return settled

    # -- the link to the CEDDP (arpz/robot/link_monitor.py) --------------------------------------

    def watch_link(self, transport: Reopenable) -> LinkWatch:
        """A ``LinkWatch`` on this robot's link to the CEDDP, reopening ``transport`` (this
        agent's transport, or the session under it) when it died; the caller starts and stops
        it. It hears the CEDDP in what ``transport`` delivers (the reliable channel's ACKNACKs
        and heartbeats, clock replies, liveliness) and in the commands, watches the CEDDP's
        presence token, and (``[link] watch_address``) the robot's source address towards every
        ``connect`` endpoint, unless all are ``quic/`` (QUIC moves to a new address itself)."""
        cfg = self.config
        self.transport.watch_liveliness(keys.ceddp_presence_key(cfg.fleet), self._on_ceddp)
        targets: list[tuple[str, int]] = []
        if cfg.link.watch_address and not all(e.startswith("quic/") for e in cfg.connect):
            targets = _route_targets(cfg.connect)

        def signals() -> Signals:
            return self.link_signals(transport.delivered, targets)

        return LinkWatch(cfg.link, transport, signals)

    def _on_ceddp(self, _key: str, alive: bool) -> None:
        self._ceddp_present = alive

    def link_signals(self, delivered: int, targets: list[tuple[str, int]] | None = None) -> Signals:
        """What this robot heard from the CEDDP (``delivered``: what its transport handed to
        callbacks so far, and the commands) and what it asked of it (samples its reliable
        writers wait to have acknowledged, clock requests), as ``Signals``; with ``targets``,
        its source address towards each."""
        readings: list[tuple[str, bool, int, int]] = []
        for outlet in self._outlets():
            stats = outlet.stats()
            acked = outlet.acknowledged_through()
            if stats is None or acked is None:
                continue  # plain mode: nothing is acknowledged
            readings.append((outlet.key, outlet.matched, acked, stats.sent))
        return Signals(
            heard=delivered + self.commands.received,
            asked=self._waiting.update(readings) + self.clock_sync.requests,
            present=self._ceddp_present,
            route=route_sources(targets) if targets else None,
        )

    def _outlets(self) -> list[Outlet | FrameOutlet]:
        outlets: list[Outlet | FrameOutlet] = [s.output for s in self.sensors]
        outlets += [self.hello_probe.outlet, self._stats_out, self._announce_out, self._ack_out]
        if self._telemetry_out is not None:
            outlets.append(self._telemetry_out)
        return outlets

    def _wait_for_readers(self, timeout_s: float) -> None:
        """A VOLATILE writer's samples (reliable channel or plain put) reach only readers matched
        when they are written: wait (bounded) until a reader matched every key, so the first
        readings are not sent into the void. Through a router mesh, a subscriber's declaration
        takes a moment to reach the robot's router; this is that moment."""
        outputs = self._outlets()
        deadline = time.monotonic() + timeout_s
        while not all(o.matched for o in outputs) and time.monotonic() < deadline:
            time.sleep(0.01)
        unmatched = [o.key for o in outputs if not o.matched]
        if unmatched:
            log.warning(
                "no reader matched %d key(s) within %.1f s (is the CEDDP running, for this "
                "robot's partition, with the same reliability and profiles?): %s",
                len(unmatched),
                timeout_s,
                ", ".join(unmatched[:3]),
            )

    def _on_incompatible(self, key: str, policy: QosPolicyKind) -> None:
        what = key or "a CEDDP writer"
        self._incompatible(
            f"{what}: {policy.value} (this robot's mode is '{self.config.reliability}')"
        )

    def _on_ceddp_mode(self, key: str, alive: bool) -> None:
        mode = key.rsplit("/", 1)[-1]
        if alive and mode != self.config.reliability:
            self._incompatible(
                f"CEDDP mode '{mode}' != this robot's '{self.config.reliability}': set "
                "reliability the same on both sides"
            )

    def _incompatible(self, text: str) -> None:
        with self.commands.lock:
            if text in self.incompatible or len(self.incompatible) >= 32:
                return
            self.incompatible.append(text)
        log.error("INCOMPATIBLE_QOS: %s", text)

    def run(self, stop: threading.Event) -> None:
        """Run the periodic jobs until ``stop`` is set or the configured duration has passed."""
        if not self._started:
            self.start()
        end_s = self.config.duration_s or float("inf")
        # without bundles, one job at a time as before them (bundles are opt-in)
        tick = self.bundler.collect if self.bundler is not None else None
        self.scheduler.run(stop, self._now_s, end_s=end_s, on_late=self._count_late, tick=tick)

    def stagger_jobs(self, fraction: float) -> None:
        """Next run each periodic job ``fraction`` (0..1) of its period from now (``Scheduler.
        stagger``): for a load generator that releases its robots together (``python -m
        arpz.perf fleet``), so that their sensing ticks, reports, probes and clock exchanges are
        spread over each period as independent robots' are."""
        self.scheduler.stagger(self._now_s(), fraction)

    def run_due(self) -> float:
        """Run the periodic jobs due now, as ``run`` does, without waiting; seconds until the
        next is due. For a load generator that drives several robots from one thread (the
        configured duration is then the caller's to keep)."""
        if not self._started:
            raise RuntimeError("RobotAgent.run_due before start()")
        tick = self.bundler.collect if self.bundler is not None else None
        now_s = self._now_s()
        return self.scheduler.run_due(now_s, on_late=self._count_late, tick=tick) - now_s

    def shutdown(self) -> None:
        """Wait (bounded) for Hellos in flight, report final stats, stop the actuator."""
        if self.config.hello.enabled:
            self.hello_probe.drain(self.config.hello.timeout_s)
        self.commands.close()
        self.configuration.close()
        self.services.close()
        self.actuator.stop()
        for sensor in self.sensors:  # a camera's last frame goes out before the drain
            sensor.stop_sending()
        # what the sensors sent and the CEDDP has not acknowledged yet: waited for while the
        # CEDDP makes progress on it (an overloaded one drains for seconds), so that it arrives
        # instead of being counted lost, and the final report is not queued behind it
        drained = drain(
            [sensor.output for sensor in self.sensors],
            stall_s=_FINAL_REPORT_WAIT_S,
            limit_s=_DRAIN_LIMIT_S,
        )
        if not drained:
            log.warning(
                "sensor samples still unacknowledged at shutdown (no progress for %.1f s, or "
                "%.0f s in all): closing; what never arrives, the CEDDP counts lost",
                _FINAL_REPORT_WAIT_S,
                _DRAIN_LIMIT_S,
            )
        for sensor in self.sensors:
            sensor.close(0.0)  # waited for above
        self.hello_probe.outlet.close()
        for outlet in (self._announce_out, self._ack_out, self._telemetry_out):
            if outlet is not None:
                outlet.close()
        # The final report carries the channel's last counters; through the channel the robot
        # waits (bounded) for the CEDDP's acknowledgement, so reconciliation never misses it.
        self._publish_stats(final=True)
        for sensor in self.sensors:  # the run's last word on a failing sensor
            if sensor.driver_errors:
                log.warning(
                    "sensor %s: %d of %d reads gave no reading in this run (last: %s)",
                    sensor.config.name,
                    sensor.driver_errors,
                    sensor.cache.counters.produced + sensor.driver_errors,
                    sensor.last_driver_error,
                )
        self.final_acknowledged = self._stats_out.close(_FINAL_REPORT_WAIT_S)
        if not self.final_acknowledged:
            log.warning(
                "final report not acknowledged within %.1f s (is the CEDDP still running?)",
                _FINAL_REPORT_WAIT_S,
            )

    # -- jobs -----------------------------------------------------------------------------------

    def _make_scheduler(self) -> Scheduler:
        cfg = self.config
        scheduler = Scheduler()
        for sensor in self.sensors:
            job = scheduler.every(
                1.0 / sensor.rate_hz,
                functools.partial(sense, sensor, writer=self.writer),
                sensor.config.name,
                in_tick=True,
            )
            self._sensor_jobs.append((sensor, job))
        if cfg.hello.enabled:
            scheduler.every(1.0 / cfg.hello.rate_hz, self.hello_probe.send, keys.HELLO)
        if self.sim is not None and cfg.sim is not None:
            scheduler.every(1.0 / cfg.sim.step_hz, self.sim.step, "sim-step")
            scheduler.every(1.0 / cfg.sim.telemetry_hz, self._send_telemetry, "telemetry")
        deadlines = self.watchdog.deadlines_s
        if deadlines:
            # checked at a tenth of the shortest deadline: a stop comes at most 10 % late
            period = max(min(deadlines.values()) / 10, 0.005)
            scheduler.every(period, self.commands.check_watchdog, "watchdog")
        if cfg.clock.enabled:
            scheduler.every(
                cfg.clock.period_s, self.clock_sync.exchange, "clock", first_s=cfg.clock.period_s
            )
        scheduler.every(
            cfg.stats_period_s,
            lambda now: self._publish_stats(final=False),
            "stats",
            first_s=cfg.stats_period_s,
        )
        scheduler.every(
            cfg.announce_period_s,
            self._publish_announce,
            "announce",
            first_s=cfg.announce_period_s,
        )
        return scheduler

    def _send_telemetry(self, now_s: float) -> None:
        assert self.sim is not None
        pose = self.sim.body.pose
        self._telemetry_seq += 1
        telemetry = Telemetry(
            writer=self.writer,
            seq=self._telemetry_seq,
            stamp_ns=self._wall_ns(),
            x_m=pose.x_m,
            y_m=pose.y_m,
            theta_rad=pose.theta_rad,
            collided=self.sim.body.collided,
        )
        assert self._telemetry_out is not None
        self._telemetry_out.send(encode(telemetry), telemetry.stamp_ns)

    def _count_late(self, late: Job, ticks: int) -> None:
        for sensor, job in self._sensor_jobs:
            if job is late:
                sensor.late_ticks += ticks
        log.debug("job %s fell %d periods behind", late.name, ticks)

    # -- the QoS assignment (on the command worker) -----------------------------------------------

    def _heartbeat_s(self, qos: RobotQos) -> float | None:
        """The sensor writers' heartbeat period: the assignment's, else (None) the robot's own
        [sensor_qos] one, so that a link measured lossless again gets its period back."""
        if qos.heartbeat_period_s is not None:
            return qos.heartbeat_period_s
        own = self.config.profile("sensor")
        return None if own is None else own.heartbeat_period_s

    def _on_qos(self, message: QosAssignmentMsg) -> None:
        """Apply the CEDDP's R and D without restarting, or refuse; answer either way."""
        cfg = self.config
        decision = decide(cfg.robot_id, message, [s.config for s in self.sensors])
        if decision.qos is None and not decision.applies and cfg.robot_id not in message.robots:
            return  # an assignment for a fleet this robot is not (yet) part of
        if decision.applies and decision.qos is not None:
            for sensor, job in self._sensor_jobs:
                # per topic (mode "per_topic") or the robot's one R and D (seed 001)
                own = decision.for_topic(sensor.config.name) or decision.qos
                sensor.rate_hz = own.rate_hz
                # the scheduler picks the new period up at the sensor's next tick
                job.period_s = 1.0 / own.rate_hz
                sensor.output.retune(
                    depth=own.depth,
                    deadline_s=own.deadline_s,
                    heartbeat_period_s=self._heartbeat_s(own),
                )
            self.qos = decision.qos
            self.qos_epoch = message.epoch
            log.info(
                "QoS epoch %d applied: %.2f Hz, deadline %.4f s, depth %d, heartbeat %s",
                message.epoch,
                decision.qos.rate_hz,
                decision.qos.deadline_s,
                decision.qos.depth,
                "as configured"
                if decision.qos.heartbeat_period_s is None
                else f"{decision.qos.heartbeat_period_s:.3f} s",
            )
            self._publish_announce(0.0)
        else:
            self.qos_refused += 1
            log.warning("QoS epoch %d refused: %s", message.epoch, decision.reason)
        current_rate = self.sensors[0].rate_hz if self.sensors else 0.0
        writer_qos = self.sensors[0].output.qos if self.sensors else None
        ack = QosAck(
            robot=cfg.robot_id,
            incarnation=self.incarnation,
            ceddp=message.ceddp,
            epoch=message.epoch,
            stamp_ns=self._wall_ns(),
            status="applied" if decision.applies else "refused",
            reason=decision.reason,
            rate_hz=current_rate,
            depth=self.qos.depth if self.qos else 0,
            heartbeat_period_s=writer_qos.heartbeat_period_s if writer_qos else None,
        )
        self._ack_out.send(encode(ack), ack.stamp_ns)

    # -- reporting ------------------------------------------------------------------------------

    def counters(self) -> dict[str, TopicCounters]:
        return {sensor.config.name: sensor.counters() for sensor in self.sensors}

    def inbound(self) -> dict[str, InboundCounters]:
        """The downlink's counters per CEDDP -> robot key (see ``CommandWorker.inbound``)."""
        return self.commands.inbound()

    def stats(self, *, final: bool, rates: bool = True) -> RobotStats:
        """This robot's report. ``rates=False``: the counters only, without measuring the
        rates (and CPU) over the interval since the last report, which would shorten the next
        report's interval (for a summary written between reports)."""
        if rates:
            reading = PROCESS_CPU.read()  # the process's, shared by the robots in it
            percent = cpu_percent(self._last_cpu, reading)
            if percent is not None:
                self._last_cpu, self._cpu_percent = reading, percent
        now, last_now = time.monotonic(), self._last_report_s
        counters = self.counters()
        rated: dict[str, TopicCounters] = dict(counters)
        interval_s = max(now - last_now, 1e-9)
        now_s = now - self._start_s  # the scheduler's clock, which ``sense`` notes readings on
        silent = [s.config.name for s in self.sensors if s.silent(now_s, interval_s)]
        if rates:
            self._last_report_s = now
        for sensor in self.sensors if rates else ():
            c = counters[sensor.config.name]
            rate = (c.sent - sensor.sent_at_last_report) / interval_s
            produced_rate = (c.produced - sensor.produced_at_last_report) / interval_s
            sensor.sent_at_last_report = c.sent
            sensor.produced_at_last_report = c.produced
            rated[sensor.config.name] = msgspec.structs.replace(
                c, rate_hz=round(rate, 3), produced_rate_hz=round(produced_rate, 3)
            )
        with self.commands.lock:
            received, errors = self.commands.received, self.commands.decode_errors
            watchdog = self.watchdog.snapshot()
            incompatible = list(self.incompatible)
        inbound = self.inbound()
        hello = self.hello.stats()
        bundles = self.bundler.stats if self.bundler is not None else None
        return RobotStats(
            robot=self.config.robot_id,
            incarnation=self.incarnation,
            stamp_ns=self._wall_ns(),
            final=final,
            topics=rated,
            commands_received=received,
            command_decode_errors=errors,
            hello=hello if (self.config.hello.enabled or hello.relayed) else None,
            cpu_percent=round(self._cpu_percent, 2),
            qos_epoch=self.qos_epoch,
            qos_rate_hz=self.qos.rate_hz if self.qos else None,
            qos_depth=self.qos.depth if self.qos else None,
            inbound=inbound,
            commands_expired=sum(
                c.lifespan_expired for name, c in inbound.items() if name.startswith("cmd/")
            ),
            watchdog_stops=dict(watchdog["stops"]),
            watchdog_stopped=list(watchdog["stopped"]),
            incompatible_qos=incompatible,
            mode=self.config.reliability,
            clock=self._clock_stats(),
            arpz_version=self._versions[0],
            zenoh_version=self._versions[1],
            bundled_messages=bundles.bundled if bundles else 0,
            bundles=bundles.bundles if bundles else 0,
            bundle_put_failures=bundles.put_failures if bundles else 0,
            silent_sensors=silent,
            started_ns=self.started_ns,
            services=self.services.counters(),
        )

    def _clock_stats(self) -> ClockStats | None:
        return self.clock_sync.stats() if self.config.clock.enabled else None

    def _publish_stats(self, *, final: bool) -> None:
        stats = self.stats(final=final)
        if final:
            self.final_stats = stats
        self._stats_out.send(encode(stats), stats.stamp_ns)

    def _topic_info(self, sensor: SensorChannel) -> TopicInfo:
        config = sensor.config
        typed = config.type is not None and self.types is not None
        return TopicInfo(
            topic=config.name,
            kind=config.kind,
            rate_hz=sensor.rate_hz,
            value_type="message" if typed else value_type_of(config.kind),
            priority=config.priority,
            max_rate_hz=config.max_rate_hz,
            configured_rate_hz=config.rate_hz,
            msg_type=config.type or "",
            type_hash=self._type_hashes.get(config.name, ""),
        )

    def _publish_announce(self, now_s: float) -> None:
        cfg = self.config
        announce = Announce(
            robot=cfg.robot_id,
            incarnation=self.incarnation,
            sensors=[self._topic_info(s) for s in self.sensors],
            commands=[keys.HELLO, *self.command_names],
            command_types=dict(self.actuator.command_types),
            services=self.services.announced(),
            mode=cfg.reliability,
            clock=self._clock_stats(),
        )
        self._announce_out.send(encode(announce), self._wall_ns())


class DuplicateRobotError(ArpzError):
    """Another process of the fleet runs with this robot's ``robot_id``."""


#: how long a starting robot waits for the router to tell it of a presence token on its key
#: (the router answers in one round trip: 5 ms on loopback; every robot start pays this wait)
PRESENCE_HISTORY_S = 0.3


class _OtherRun:
    """What a starting robot hears of another process with its robot_id (Zenoh callbacks:
    record and signal, nothing that waits)."""

    def __init__(self) -> None:
        self.changed = threading.Event()
        self.alive: bool | None = None
        #: (incarnation, started_ns) of a report from the other process
        self.report: tuple[str, int] | None = None

    def on_token(self, _key: str, alive: bool) -> None:
        self.alive = alive
        self.changed.set()

    def on_report(self, key: str, payload: bytes, _attachment: bytes | None) -> None:
        try:
            if key.endswith("/stats"):
                stats = STATS_DECODER.decode(payload)
                if stats.final:
                    return  # its last words: it is stopping
                self.report = (stats.incarnation, stats.started_ns)
            else:
                self.report = (ANNOUNCE_DECODER.decode(payload).incarnation, 0)
        except DECODE_ERRORS:
            return
        self.changed.set()


def check_robot_id_free(
    transport: Transport,
    config: RobotConfig,
    *,
    linger_s: float,
    history_s: float = PRESENCE_HISTORY_S,
) -> float:
    """Raise ``DuplicateRobotError`` when another process runs as ``config.robot_id`` in the
    fleet; call before the agent declares anything. Returns how long it waited.

    The other process's presence token is the sign. It can also be a previous run of this robot
    that ended without closing its session (a crash, a power cut): the router keeps its token
    until the lease of that session ends. So, while the token is alive, the robot waits for
    either: the token to vanish (a previous run: go on), a report (stats or announcement) from
    the other process (it runs: refused at once), or ``linger_s`` to pass (the lease: refused).
    Under access control the rules of deploy/tls/make_fleet_certs.py let a robot see its own
    token; rules that do not leave the CEDDP's check to catch a duplicate (docs/operations.md)."""
    fleet, robot = config.fleet, config.robot_id
    other = _OtherRun()
    started = time.monotonic()
    handles = [transport.watch_liveliness(keys.presence_key(fleet, robot), other.on_token)]
    try:
        other.changed.wait(history_s)
        if not other.alive:
            return time.monotonic() - started
        log.warning(
            "a presence token of robot %s is alive before this process declared its own: "
            "waiting up to %.1f s for it to go (a previous run that ended without closing its "
            "session) or to hear from the process that holds it",
            robot,
            linger_s,
        )
        for key in (keys.stats_key(fleet, robot), keys.announce_key(fleet, robot)):
            handles.append(transport.subscribe(key, other.on_report))
        deadline = started + history_s + linger_s
        while other.alive and other.report is None:
            left = deadline - time.monotonic()
            if left <= 0:
                break
            other.changed.clear()
            if other.alive and other.report is None:
                other.changed.wait(min(left, 0.1))
        waited = time.monotonic() - started
        if not other.alive:
            log.info("the previous run's presence token of robot %s vanished", robot)
            return waited
    finally:
        for handle in handles:
            handle.undeclare()
    fix = (
        "give each robot its own robot_id (robot_id in its TOML, or --robot-id), or stop the "
        "other process first"
    )
    if other.report is not None:
        incarnation, started_ns = other.report
        since = (
            f", started {time.strftime('%Y-%m-%d %H:%M:%S', time.gmtime(started_ns / 1e9))} UTC"
            if started_ns
            else ""
        )
        raise DuplicateRobotError(
            f"robot_id '{robot}' is in use: another process runs as {robot} in fleet "
            f"'{fleet}' (incarnation {incarnation}{since}, reporting on "
            f"{keys.stats_key(fleet, robot)}); {fix}"
        )
    raise DuplicateRobotError(
        f"robot_id '{robot}' is in use: the presence token {keys.presence_key(fleet, robot)} "
        f"of another process stayed alive {waited:.1f} s, longer than a session that ended "
        f"lingers (the lease, {linger_s:.1f} s), and it sent no report; {fix}"
    )


def _route_targets(endpoints: list[str]) -> list[tuple[str, int]]:
    """(address, port) of each IP endpoint, names resolved once (a name that does not resolve
    now is left out: its route cannot be watched)."""
    targets: list[tuple[str, int]] = []
    for endpoint in endpoints:
        address = endpoint_address(endpoint)
        if address is None:
            continue
        host, port = address
        try:
            infos = socket.getaddrinfo(host, port, type=socket.SOCK_DGRAM)
        except OSError as exc:
            log.warning(
                "the route to %s is not watched: %s does not resolve (%s)", endpoint, host, exc
            )
            continue
        if infos:
            targets.append((str(infos[0][4][0]), port))
    return targets
