"""The robot agent: sensing through the local cache, actuation, presence and self-reporting.

Threads: one scheduler thread runs every periodic job (each sensor at its rate, the Hello probe,
stats and announcements) from a heap of due times, so a robot with many sensors does not need a
thread per sensor; one command worker decodes commands handed over by the Zenoh callback through
a queue, so the callback never blocks.
"""

from __future__ import annotations

import functools
import heapq
import logging
import queue
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import msgspec

from arpz import keys
from arpz.config import RobotConfig, SensorConfig
from arpz.messages import (
    COMMAND_DECODER,
    DECODE_ERRORS,
    HELLO_DECODER,
    QOS_ASSIGNMENT_DECODER,
    Announce,
    Hello,
    QosAck,
    QosAssignmentMsg,
    RobotQos,
    RobotStats,
    Sample,
    Telemetry,
    TopicCounters,
    TopicInfo,
    encode,
    new_incarnation,
    writer_id,
)
from arpz.robot.actuation import Actuator, RecordingActuator
from arpz.robot.hello import HelloTracker
from arpz.robot.local_cache import LocalCache
from arpz.robot.output import SensorOutput
from arpz.robot.qos import decide
from arpz.robot.sensors import SensorDriver, make_driver, preset_sensors, value_type_of
from arpz.robot.sensors.base import check_value
from arpz.robot.sim_host import BeamDriver, SimActuator, SimHost
from arpz.transport import Transport

log = logging.getLogger(__name__)

#: the command topics every agent listens on, beyond what its actuator declares
HELLO_TOPIC = "hello"
#: how long the robot waits after its last report before closing its Zenoh session
_FINAL_REPORT_LINGER_S = 0.1


def effective_sensors(config: RobotConfig) -> list[SensorConfig]:
    """The preset's sensors, then the explicit ones (an explicit sensor replaces a preset one
    of the same name)."""
    explicit = {s.name: s for s in config.sensors}
    base = preset_sensors(config.preset, config.preset_rate_hz) if config.preset else []
    merged = [explicit.pop(s.name, s) for s in base]
    return merged + [s for s in config.sensors if s.name in explicit]


@dataclass
class _SensorChannel:
    config: SensorConfig
    driver: SensorDriver
    cache: LocalCache
    output: SensorOutput
    seq: int = 0
    bytes_sent: int = 0
    driver_errors: int = 0
    late_ticks: int = 0
    sent_at_last_report: int = 0
    produced_at_last_report: int = 0
    #: the rate the scheduler runs this sensor at (the config's, until a QoS assignment)
    rate_hz: float = 0.0


@dataclass(order=True)
class _Job:
    due_s: float
    order: int
    period_s: float = field(compare=False)
    run: Callable[[float], None] = field(compare=False)
    name: str = field(compare=False)


class RobotAgent:
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
        self.hello = HelloTracker(config.hello.timeout_s)
        self.commands_received = 0
        self.command_decode_errors = 0
        self._counter_lock = threading.Lock()
        self._commands: queue.SimpleQueue[tuple[str, bytes] | None] = queue.SimpleQueue()
        self._hello_seq = 0
        self._hello_writer_seq = 0
        self._hello_lock = threading.Lock()
        self._hello_out = SensorOutput(
            transport,
            keys.sensor_key(config.fleet, config.robot_id, HELLO_TOPIC),
            config.sensor_qos,
        )
        self._start_s = time.monotonic()
        self._last_cpu = (time.monotonic(), time.process_time())
        self._telemetry_seq = 0
        self.sensors: list[_SensorChannel] = []
        sensor_configs = effective_sensors(config)
        if self.sim is not None and config.sim is not None:
            sensor_configs = self.sim.beam_sensors(config.sim.beam_rate_hz) + sensor_configs
        for sensor in sensor_configs:
            silence = sensor.max_silence_s or config.local_cache.max_silence_s
            self.sensors.append(
                _SensorChannel(
                    config=sensor,
                    driver=BeamDriver(self.sim, sensor.name)
                    if self.sim is not None and sensor.driver == "sim-body"
                    else make_driver(
                        sensor, robot_id=config.robot_id, robot_seed=config.seed, base_dir=base_dir
                    ),
                    cache=LocalCache(
                        enabled=config.local_cache.enabled,
                        tolerance=sensor.tolerance,
                        max_silence_s=silence,
                    ),
                    output=SensorOutput(
                        transport,
                        keys.sensor_key(config.fleet, config.robot_id, sensor.name),
                        config.sensor_qos,
                    ),
                    rate_hz=sensor.rate_hz,
                )
            )
        #: the QoS the CEDDP assigned and this robot applied (None: running its own config)
        self.qos: RobotQos | None = None
        self.qos_epoch = 0
        self.qos_refused = 0
        self._jobs = self._make_jobs()
        self._sensor_jobs = {job.name: job for job in self._jobs}
        self._worker = threading.Thread(
            target=self._command_loop, name="arpz-commands", daemon=True
        )
        self._started = False

    # -- life cycle ---------------------------------------------------------------------------

    def start(self) -> None:
        """Subscribe to commands, announce presence; sensing starts in ``run``."""
        cfg = self.config
        self._worker.start()
        self.transport.subscribe(
            f"{keys.robot_prefix(cfg.fleet, cfg.robot_id)}/cmd/*",
            lambda key, payload, _att: self._commands.put((key, payload)),
        )
        self.transport.subscribe(
            keys.ceddp_qos_key(cfg.fleet),
            lambda key, payload, _att: self._commands.put((key, payload)),
        )
        self.transport.declare_token(keys.presence_key(cfg.fleet, cfg.robot_id))
        self._publish_announce(0.0)
        self._wait_for_readers(cfg.match_timeout_s)
        self._started = True
        log.info(
            "robot %s (%s) started with %d sensors",
            cfg.robot_id,
            self.incarnation,
            len(self.sensors),
        )

    def _wait_for_readers(self, timeout_s: float) -> None:
        """A VOLATILE writer's samples (reliable channel or plain put) reach only readers matched
        when they are written: wait (bounded) until a reader matched every topic, so the first
        readings are not sent into the void. Through a router mesh, a subscriber's declaration
        takes a moment to reach the robot's router; this is that moment."""
        outputs = [s.output for s in self.sensors] + [self._hello_out]
        deadline = time.monotonic() + timeout_s
        while not all(o.matched for o in outputs) and time.monotonic() < deadline:
            time.sleep(0.01)
        unmatched = [o.key for o in outputs if not o.matched]
        if unmatched:
            log.warning(
                "no reader matched %d topic(s) within %.1f s (is the CEDDP running, for this "
                "robot's partition, with the same sensor_qos?): %s",
                len(unmatched),
                timeout_s,
                ", ".join(unmatched[:3]),
            )

    def run(self, stop: threading.Event) -> None:
        """Run the periodic jobs until ``stop`` is set or the configured duration has passed."""
        if not self._started:
            self.start()
        jobs = self._jobs
        heapq.heapify(jobs)
        end_s = self.config.duration_s or float("inf")
        while not stop.is_set():
            now_s = time.monotonic() - self._start_s
            if now_s >= end_s:
                break
            job = jobs[0]
            if job.due_s > now_s:
                stop.wait(min(job.due_s - now_s, 0.05))
                continue
            job.run(now_s)
            job.due_s += job.period_s
            if job.due_s < now_s - job.period_s:
                # fell more than a period behind (a slow driver or an overloaded CPU): count it
                # and re-align instead of bursting to catch up
                self._count_late(job.name, int((now_s - job.due_s) / job.period_s))
                job.due_s = now_s + job.period_s
            heapq.heapreplace(jobs, job)

    def shutdown(self) -> None:
        """Wait (bounded) for Hellos in flight, report final stats, stop the actuator."""
        if self.config.hello.enabled:
            deadline = time.monotonic() + self.config.hello.timeout_s
            while self.hello.outstanding and time.monotonic() < deadline:
                time.sleep(0.01)
            self.hello.expire(time.time_ns(), all_outstanding=True)
        self._commands.put(None)
        self._worker.join(timeout=2.0)
        self._publish_stats(final=True)
        self.actuator.stop()
        for sensor in self.sensors:
            sensor.driver.close()
            sensor.output.close()
        self._hello_out.close()
        # The final report is a plain put (no recovery) and the CEDDP's reconciliation needs it:
        # send it again, with the channel's last counters, and give it time to leave before the
        # session closes. The CEDDP keeps the latest final report, so a repeat costs nothing.
        self._publish_stats(final=True)
        time.sleep(_FINAL_REPORT_LINGER_S)

    # -- jobs -----------------------------------------------------------------------------------

    def _make_jobs(self) -> list[_Job]:
        cfg = self.config
        jobs: list[_Job] = []
        for sensor in self.sensors:
            jobs.append(
                _Job(
                    0.0,
                    len(jobs),
                    1.0 / sensor.rate_hz,
                    functools.partial(self._sense, sensor),
                    sensor.config.name,
                )
            )
        if cfg.hello.enabled:
            jobs.append(_Job(0.0, len(jobs), 1.0 / cfg.hello.rate_hz, self._send_hello, "hello"))
        if self.sim is not None and cfg.sim is not None:
            sim = self.sim
            jobs.append(_Job(0.0, len(jobs), 1.0 / cfg.sim.step_hz, sim.step, "sim-step"))
            jobs.append(
                _Job(0.0, len(jobs), 1.0 / cfg.sim.telemetry_hz, self._send_telemetry, "telemetry")
            )
        jobs.append(
            _Job(
                cfg.stats_period_s,
                len(jobs),
                cfg.stats_period_s,
                lambda now: self._publish_stats(final=False),
                "stats",
            )
        )
        jobs.append(
            _Job(
                cfg.announce_period_s,
                len(jobs),
                cfg.announce_period_s,
                self._publish_announce,
                "announce",
            )
        )
        return jobs

    def _sense(self, sensor: _SensorChannel, now_s: float) -> None:
        try:
            value = check_value(sensor.config.kind, sensor.driver.read(now_s))
        except Exception as exc:  # a driver bug or a device error must not stop the robot
            sensor.driver_errors += 1
            if sensor.driver_errors in (1, 10, 100) or sensor.driver_errors % 1000 == 0:
                log.error(
                    "sensor %s: driver error #%d: %s", sensor.config.name, sensor.driver_errors, exc
                )
            return
        if not sensor.cache.offer(value, now_s):
            sensor.output.unchanged()
            return
        stamp_ns = time.time_ns()
        payload = encode(Sample(self.writer, sensor.seq + 1, stamp_ns, value))
        if sensor.output.send(payload, stamp_ns):
            sensor.seq += 1
            sensor.bytes_sent += len(payload)
        else:
            sensor.cache.forget()

    def _send_hello(self, now_s: float) -> None:
        with self._hello_lock:
            self._hello_seq += 1
            origin_seq = self._hello_seq
        t0_ns = time.time_ns()
        self.hello.on_sent(origin_seq, t0_ns)
        self._put_hello(Hello(self.writer, 0, 0, self.config.robot_id, origin_seq, t0_ns, 0))
        self.hello.expire(time.time_ns())

    def _put_hello(self, hello: Hello) -> None:
        with self._hello_lock:
            self._hello_writer_seq += 1
            seq = self._hello_writer_seq
        stamped = msgspec.structs.replace(
            hello, writer=self.writer, seq=seq, stamp_ns=time.time_ns()
        )
        self._hello_out.send(encode(stamped), stamped.stamp_ns)

    def _send_telemetry(self, now_s: float) -> None:
        assert self.sim is not None
        pose = self.sim.body.pose
        self._telemetry_seq += 1
        telemetry = Telemetry(
            writer=self.writer,
            seq=self._telemetry_seq,
            stamp_ns=time.time_ns(),
            x_m=pose.x_m,
            y_m=pose.y_m,
            theta_rad=pose.theta_rad,
            collided=self.sim.body.collided,
        )
        self.transport.put(
            keys.telemetry_key(self.config.fleet, self.config.robot_id), encode(telemetry)
        )

    def _count_late(self, job_name: str, ticks: int) -> None:
        for sensor in self.sensors:
            if sensor.config.name == job_name:
                sensor.late_ticks += ticks
        log.debug("job %s fell %d periods behind", job_name, ticks)

    # -- commands -------------------------------------------------------------------------------

    def _command_loop(self) -> None:
        while True:
            item = self._commands.get()
            if item is None:
                return
            key, payload = item
            name = key.rsplit("/", 1)[-1]
            with self._counter_lock:
                self.commands_received += 1
            try:
                if key == keys.ceddp_qos_key(self.config.fleet):
                    self._on_qos(QOS_ASSIGNMENT_DECODER.decode(payload))
                elif name == HELLO_TOPIC:
                    self._on_hello(HELLO_DECODER.decode(payload))
                else:
                    self.actuator.apply(name, COMMAND_DECODER.decode(payload))
            except DECODE_ERRORS as exc:
                with self._counter_lock:
                    self.command_decode_errors += 1
                log.warning("undecodable command on %s (%d bytes): %s", key, len(payload), exc)
            except Exception:
                log.exception("actuator failed on a command on %s", key)

    def _on_qos(self, message: QosAssignmentMsg) -> None:
        """Apply the CEDDP's R and D without restarting, or refuse; answer either way."""
        cfg = self.config
        decision = decide(cfg.robot_id, message, [s.config for s in self.sensors])
        if decision.qos is None and not decision.applies and cfg.robot_id not in message.robots:
            return  # an assignment for a fleet this robot is not (yet) part of
        if decision.applies and decision.qos is not None:
            for sensor in self.sensors:
                sensor.rate_hz = decision.qos.rate_hz
                # the scheduler picks the new period up at the sensor's next tick
                self._sensor_jobs[sensor.config.name].period_s = 1.0 / decision.qos.rate_hz
                sensor.output.retune(depth=decision.qos.depth, deadline_s=decision.qos.deadline_s)
            self.qos = decision.qos
            self.qos_epoch = message.epoch
            log.info(
                "QoS epoch %d applied: %.2f Hz, deadline %.4f s, depth %d",
                message.epoch,
                decision.qos.rate_hz,
                decision.qos.deadline_s,
                decision.qos.depth,
            )
            self._publish_announce(0.0)
        else:
            self.qos_refused += 1
            log.warning("QoS epoch %d refused: %s", message.epoch, decision.reason)
        current_rate = self.sensors[0].rate_hz if self.sensors else 0.0
        ack = QosAck(
            robot=cfg.robot_id,
            incarnation=self.incarnation,
            ceddp=message.ceddp,
            epoch=message.epoch,
            stamp_ns=time.time_ns(),
            status="applied" if decision.applies else "refused",
            reason=decision.reason,
            rate_hz=current_rate,
            depth=self.qos.depth if self.qos else 0,
        )
        self.transport.put(keys.qos_ack_key(cfg.fleet, cfg.robot_id), encode(ack))

    def _on_hello(self, hello: Hello) -> None:
        if hello.stage == 1:
            self.hello.on_relayed()
            self._put_hello(msgspec.structs.replace(hello, stage=2))
        elif hello.stage == 3 and hello.origin == self.config.robot_id:
            self.hello.on_returned(hello.origin_seq, time.time_ns())
        else:
            with self._counter_lock:
                self.command_decode_errors += 1
            log.warning("unexpected Hello stage %d from %s", hello.stage, hello.writer)

    # -- reporting ------------------------------------------------------------------------------

    def counters(self) -> dict[str, TopicCounters]:
        out: dict[str, TopicCounters] = {}
        for sensor in self.sensors:
            c = sensor.cache.counters
            channel = sensor.output.totals()
            out[sensor.config.name] = TopicCounters(
                produced=c.produced,
                # a reading the cache passed but a full KEEP_ALL history refused was not sent
                sent=c.sent - channel["write_failures"],
                held_back=c.held_back,
                last_seq=sensor.seq,
                bytes_sent=sensor.bytes_sent,
                write_failures=channel["write_failures"],
                retransmitted=channel["retransmitted"],
                gapped=channel["gapped"],
                overwritten_unacked=channel["overwritten_unacked"],
                deadline_missed=channel["deadline_missed"],
            )
        return out

    def stats(self, *, final: bool) -> RobotStats:
        now, cpu = time.monotonic(), time.process_time()
        last_now, last_cpu = self._last_cpu
        self._last_cpu = (now, cpu)
        cpu_percent = 100.0 * (cpu - last_cpu) / (now - last_now) if now > last_now else 0.0
        counters = self.counters()
        rated: dict[str, TopicCounters] = {}
        interval_s = max(now - last_now, 1e-9)
        for sensor in self.sensors:
            c = counters[sensor.config.name]
            rate = (c.sent - sensor.sent_at_last_report) / interval_s
            produced_rate = (c.produced - sensor.produced_at_last_report) / interval_s
            sensor.sent_at_last_report = c.sent
            sensor.produced_at_last_report = c.produced
            rated[sensor.config.name] = msgspec.structs.replace(
                c, rate_hz=round(rate, 3), produced_rate_hz=round(produced_rate, 3)
            )
        with self._counter_lock:
            received, errors = self.commands_received, self.command_decode_errors
        hello = self.hello.stats()
        return RobotStats(
            robot=self.config.robot_id,
            incarnation=self.incarnation,
            stamp_ns=time.time_ns(),
            final=final,
            topics=rated,
            commands_received=received,
            command_decode_errors=errors,
            hello=hello if (self.config.hello.enabled or hello.relayed) else None,
            cpu_percent=round(cpu_percent, 2),
            qos_epoch=self.qos_epoch,
            qos_rate_hz=self.qos.rate_hz if self.qos else None,
            qos_depth=self.qos.depth if self.qos else None,
        )

    def _publish_stats(self, *, final: bool) -> None:
        stats = self.stats(final=final)
        self.transport.put(keys.stats_key(self.config.fleet, self.config.robot_id), encode(stats))

    def _publish_announce(self, now_s: float) -> None:
        cfg = self.config
        announce = Announce(
            robot=cfg.robot_id,
            incarnation=self.incarnation,
            sensors=[
                TopicInfo(
                    topic=s.config.name,
                    kind=s.config.kind,
                    rate_hz=s.rate_hz,
                    value_type=value_type_of(s.config.kind),
                )
                for s in self.sensors
            ],
            commands=[HELLO_TOPIC, *getattr(self.actuator, "commands", [])],
        )
        self.transport.put(keys.announce_key(cfg.fleet, cfg.robot_id), encode(announce))
