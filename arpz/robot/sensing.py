"""One sensor of a robot, from its driver through the local cache to its channel writer.

``SensorChannel`` holds what the robot keeps per sensor (driver, local cache, outlet, counters);
``sense`` is one scheduler tick of it: read, let the local cache decide, and either send the
sample or tell the channel the value is unchanged (an UNCHANGED heartbeat keeps the CEDDP fresh).
"""

from __future__ import annotations

import collections
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from time import perf_counter

import msgspec

from arpz.channel.io import FrameOutlet, Outlet
from arpz.core import keys
from arpz.core.config import LARGE_SAMPLE_BYTES, RobotConfig, SensorConfig
from arpz.core.endpoints import frame_fragment_bytes
from arpz.core.messages import (
    LargeSample,
    MessageSample,
    Sample,
    TopicCounters,
    encode,
)
from arpz.core.msgtypes import MessageTypeError, MessageTypes, MessageValueError, same_message
from arpz.core.throttled_log import ThrottledLog
from arpz.core.transport import Transport
from arpz.robot.local_cache import LocalCache
from arpz.robot.sensors import SensorDriver, make_driver, preset_sensors
from arpz.robot.sensors.base import DriverValueError, check_value
from arpz.robot.sim_host import BeamDriver, SimHost

log = logging.getLogger(__name__)
#: driver errors, refusals and late reads: one line per sensor and cause every 10 s for as long
#: as the cause lasts, with the count of what it stands for (never one per read, never silent)
throttled = ThrottledLog(log)
#: the longest a driver error's text kept for the stats (``TopicCounters.last_driver_error``)
ERROR_TEXT_CHARS = 200


def effective_sensors(config: RobotConfig) -> list[SensorConfig]:
    """The preset's sensors, then the explicit ones (an explicit sensor replaces a preset one
    of the same name)."""
    explicit = {s.name: s for s in config.sensors}
    base = preset_sensors(config.preset, config.preset_rate_hz) if config.preset else []
    merged = [explicit.pop(s.name, s) for s in base]
    return merged + [s for s in config.sensors if s.name in explicit]


class FrameSender:
    """A large sensor's frames (camera, point cloud) go out on a thread of their own, so that a
    link slower than the frames never holds up the robot's scheduler and its other sensors.

    Issue 39: on a 20 Mbit/s link a 5 Hz camera got 2.8 frames/s through, and every other
    sensor of its robot fell to the same tick rate (IMU 238 readings in 60 s instead of about
    1 500): the scheduler's thread waited in the camera's write. Now ``offer`` only hands the
    frame over. While a frame is going out, a newer one waits in a single slot (the newest
    wins: a robot wants the latest picture, not a queue of old ones); the frame it replaces is
    skipped and counted (``skipped``). Memory: one frame in flight and one waiting.

    The seq is given when the frame goes out, by this thread (``SensorChannel.seq`` is its own
    for a large sensor), so a skipped or refused frame never leaves a hole in the seqs the
    CEDDP counts lost."""

    def __init__(self, sensor: SensorChannel) -> None:
        self._sensor = sensor
        self._cond = threading.Condition()
        #: (writer, value, stamp_ns, changed_ns, since_ns) of the frame waiting its turn
        self._waiting: tuple[str, bytes, int, int, int] | None = None
        self._sending = False
        self._closed = False
        #: frames replaced in the slot by a newer one before they could go out
        self.skipped = 0
        #: a write was refused (a full history): the local cache must not hold the next back
        self.refused_since_sense = False
        self._thread = threading.Thread(
            target=self._run, name=f"arpz-frames-{sensor.config.name}", daemon=True
        )
        self._thread.start()

    def offer(
        self, writer: str, value: bytes, stamp_ns: int, changed_ns: int, since_ns: int
    ) -> None:
        with self._cond:
            if self._closed:
                self.skipped += 1
                return
            if self._waiting is not None:
                self.skipped += 1
            self._waiting = (writer, value, stamp_ns, changed_ns, since_ns)
            self._cond.notify()

    @property
    def busy(self) -> bool:
        with self._cond:
            return self._sending or self._waiting is not None

    def _run(self) -> None:
        sensor = self._sensor
        while True:
            with self._cond:
                while self._waiting is None and not self._closed:
                    self._cond.wait()
                if self._waiting is None:
                    return
                writer, value, stamp_ns, changed_ns, since_ns = self._waiting
                self._waiting = None
                self._sending = True
            try:
                seq = sensor.seq + 1
                payload = encode(LargeSample(writer, seq, stamp_ns, value, changed_ns, since_ns))
                if sensor.output.send(payload, stamp_ns):
                    sensor.seq = seq
                    sensor.bytes_sent += len(payload)
                else:
                    self.refused_since_sense = True
            except Exception:  # the thread must go on: the next frame may go out
                log.exception("sensor %s: sending a frame failed", sensor.config.name)
                self.refused_since_sense = True
            finally:
                with self._cond:
                    self._sending = False
                    self._cond.notify_all()

    def close(self, timeout_s: float = 5.0) -> None:
        """Send what waits, then stop (bounded: a frame that cannot go out within ``timeout_s``
        is left to the channel's own close)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
        self._thread.join(timeout_s)


@dataclass
class SensorChannel:
    config: SensorConfig
    driver: SensorDriver
    cache: LocalCache
    output: Outlet | FrameOutlet
    seq: int = 0
    bytes_sent: int = 0
    #: reads that gave no reading: the driver raised, or its value was refused
    driver_exceptions: int = 0
    values_refused: int = 0
    #: reads that took longer than the sensor's period (sent all the same)
    late_reads: int = 0
    last_driver_error: str = ""
    #: when the driver last gave a reading (the scheduler's clock; 0: the agent's start)
    last_reading_s: float = 0.0
    late_ticks: int = 0
    sent_at_last_report: int = 0
    produced_at_last_report: int = 0
    #: the rate the scheduler runs this sensor at (the config's, until a QoS assignment)
    rate_hz: float = 0.0
    #: times the local cache forgot its last value because the channel lost the newest one
    cache_forgets: int = 0
    #: the last value read and when it was first read (staleness is measured from it)
    last_read: object = None
    changed_ns: int = 0
    #: (seq, changed_ns) of the samples sent and not yet acknowledged (channel seq == seq: one
    #: write per sample), so a sample can say since when the CEDDP may be stale if they are lost
    unacked: collections.deque[tuple[int, int]] = field(
        default_factory=lambda: collections.deque(maxlen=100_000)
    )
    #: the robot's wall clock for stamps (the agent's, which ``[clock] shift_s`` can shift)
    wall_ns: Callable[[], int] = time.time_ns
    #: a large sensor's sending thread (None: small samples go out from the scheduler's tick)
    sender: FrameSender | None = None
    #: a typed sensor's message types (None: one of the nine scalar kinds)
    types: MessageTypes | None = None

    @property
    def driver_errors(self) -> int:
        """Reads that gave no reading (``produced`` counts them)."""
        return self.driver_exceptions + self.values_refused

    def silent(self, now_s: float, interval_s: float) -> bool:
        """No reading for the last ``interval_s`` and at least two periods (only driver
        errors, or no read at all)."""
        return now_s - self.last_reading_s >= max(interval_s, 2.0 / self.rate_hz)

    def counters(self) -> TopicCounters:
        c = self.cache.counters
        channel = self.output.totals()
        skipped = self.sender.skipped if self.sender is not None else 0
        # a reading the cache passed but a full KEEP_ALL history refused, or a frame a newer
        # one replaced while the link was busy, was not sent
        not_sent = channel["write_failures"] + skipped
        errors = self.driver_errors
        return TopicCounters(
            produced=c.produced + errors,
            sent=c.sent - not_sent,
            held_back=c.held_back,
            last_seq=self.seq,
            bytes_sent=self.bytes_sent,
            write_failures=not_sent,
            frames_skipped=skipped,
            late_periods=self.late_ticks,
            retransmitted=channel["retransmitted"],
            history_offered=channel["history_offered"],
            heartbeats=channel["heartbeats"],
            gapped=channel["gapped"],
            overwritten_unacked=channel["overwritten_unacked"],
            deadline_missed=channel["deadline_missed"],
            cache_forgets=self.cache_forgets,
            driver_errors=errors,
            driver_exceptions=self.driver_exceptions,
            values_refused=self.values_refused,
            late_reads=self.late_reads,
            last_driver_error=self.last_driver_error,
        )

    def stop_sending(self) -> None:
        """A large sensor's last frame goes out, and its thread ends (before the final count)."""
        if self.sender is not None:
            self.sender.close()

    def close(self, wait_s: float = 0.5) -> None:
        """Close the driver and the channel, waiting up to ``wait_s`` for acknowledgements."""
        self.stop_sending()
        self.driver.close()
        self.output.close(wait_s)


def message_types(config: RobotConfig, base_dir: Path) -> MessageTypes | None:
    """The message types of a robot with typed sensors (the standard ones and its
    ``msg_paths``, relative to the config's folder), each sensor's type checked to be known;
    None for a robot with scalar sensors only (rosbags' types are not loaded then)."""
    typed = [s for s in config.sensors if s.type is not None]
    if not typed:
        return None
    types = MessageTypes()
    types.add_msg_paths([base_dir / path for path in config.msg_paths])
    for sensor in typed:
        assert sensor.type is not None
        try:
            types.require(sensor.type)
        except MessageTypeError as exc:
            raise MessageTypeError(f"sensor {sensor.name!r}: {exc}") from None
    return types


def build_sensors(
    config: RobotConfig,
    transport: Transport,
    sim: SimHost | None,
    base_dir: Path,
    types: MessageTypes | None = None,
) -> list[SensorChannel]:
    """Every sensor of the config (a simulated body's beams first), each with its driver, local
    cache and channel writer; ``types``: the robot's message types, for its typed sensors."""
    sensor_configs = effective_sensors(config)
    if sim is not None and config.sim is not None:
        sensor_configs = sim.beam_sensors(config.sim.beam_rate_hz) + sensor_configs
    sensors: list[SensorChannel] = []
    for sensor in sensor_configs:
        silence = sensor.max_silence_s or config.local_cache.max_silence_s
        driver = (
            BeamDriver(sim, sensor.name)
            if sim is not None and sensor.driver == "sim-body"
            else make_driver(
                sensor, robot_id=config.robot_id, robot_seed=config.seed, base_dir=base_dir
            )
        )
        channel = SensorChannel(
            config=sensor,
            driver=driver,
            cache=LocalCache(
                enabled=config.local_cache.enabled,
                tolerance=sensor.tolerance,
                max_silence_s=silence,
                same=_same_message_within(sensor.cache_deadband) if sensor.type else None,
            ),
            output=sensor_outlet(config, sensor, transport),
            rate_hz=sensor.rate_hz,
            types=types if sensor.type else None,
        )
        if isinstance(channel.output, FrameOutlet):
            channel.sender = FrameSender(channel)
        sensors.append(channel)
    return sensors


def _same_message_within(deadband: dict[str, float]) -> Callable[[object, object], bool]:
    return lambda a, b: same_message(a, b, deadband)


def sensor_outlet(
    config: RobotConfig, sensor: SensorConfig, transport: Transport
) -> Outlet | FrameOutlet:
    """A camera or point cloud through the channel goes as fragments on ``frames/{topic}``
    (``frames_qos``); every other sensor, and every sensor in plain mode, on ``sensor/{topic}``
    (with ``bundle_sensors``: unbatched, the tick's bundle being its batching)."""
    frames_qos = config.profile("frames")
    if sensor.large and frames_qos is not None:
        key = keys.frames_key(config.fleet, config.robot_id, sensor.name)
        fragment_bytes = config.frame_fragment_bytes or frame_fragment_bytes(config.connect)
        return FrameOutlet(transport, key, frames_qos, LARGE_SAMPLE_BYTES, fragment_bytes)
    key = keys.sensor_key(config.fleet, config.robot_id, sensor.name)
    qos = config.profile("sensor")
    if qos is not None and config.bundle_sensors and qos.batching:
        # The tick's bundle batches a robot's sensor messages already. A writer's own batch
        # opened only when the robot ran late and wrote a topic twice within batch_max_delay_s
        # (a catch-up tick): that sample then left the bundle and waited for the writer's
        # thread, behind the process's GIL. 50 robots, six A/B rounds: the median robot's p99
        # lower in five and equal in one (benchmarks/investigations/README.md, stop 39).
        qos = msgspec.structs.replace(qos, batch_max_samples=1)
    return Outlet(transport, key, qos)


def sense(sensor: SensorChannel, now_s: float, writer: str) -> None:
    """One tick: read the driver, hold an unchanged reading back, send a changed one. A read
    that raises, or whose value is refused, is a driver error: counted, logged (one line per
    cause every 10 s), and no sample."""
    config = sensor.config
    started = perf_counter()
    try:
        raw = sensor.driver.read(now_s)
    except Exception as exc:  # a driver bug or a device error must not stop the robot
        sensor.driver_exceptions += 1
        _driver_error(sensor, writer, type(exc).__name__, f"{type(exc).__name__}: {exc}")
        return
    took_s = perf_counter() - started
    if sensor.types is not None:
        _sense_message(sensor, now_s, writer, raw, took_s)
        return
    try:
        value = check_value(config.kind, raw)
        if type(value) is float and not math.isfinite(value) and config.nan != "pass":
            raise DriverValueError(
                f'a {config.kind} driver returned {value} (nan = "pass" in its [[sensors]] '
                "entry sends NaN and infinity)"
            )
    except DriverValueError as exc:
        sensor.values_refused += 1
        _driver_error(sensor, writer, "refused", f"value refused: {exc}")
        return
    _offer(sensor, now_s, writer, value, took_s)


def _sense_message(
    sensor: SensorChannel, now_s: float, writer: str, raw: object, took_s: float
) -> None:
    """A typed sensor's reading: the driver's message checked against the topic's type (a
    message that does not fit is a driver error, counted, never a sample), stamped if the
    driver left its header out."""
    config, types = sensor.config, sensor.types
    assert config.type is not None and types is not None
    try:
        message = types.check(
            config.type, raw, nan=config.nan, stamp_ns=sensor.wall_ns(), frame_id=config.name
        )
    except MessageValueError as exc:
        sensor.values_refused += 1
        _driver_error(sensor, writer, "refused", f"message refused: {exc}")
        return
    _offer(sensor, now_s, writer, message, took_s)


def _offer(sensor: SensorChannel, now_s: float, writer: str, value: object, took_s: float) -> None:
    """A reading the driver gave: late-read bookkeeping, the local cache, and the send."""
    config = sensor.config
    sensor.last_reading_s = now_s
    if took_s * sensor.rate_hz > 1.0:
        sensor.late_reads += 1
        throttled.warning(
            f"{writer} {config.name} late",
            "sensor %s: read took %.3f s, longer than its period of %.3f s (the reading is "
            "sent; %d late reads so far)",
            config.name,
            took_s,
            1.0 / sensor.rate_hz,
            sensor.late_reads,
        )
    stamp_ns = sensor.wall_ns()
    if sensor.last_read is None or not sensor.cache.same(value, sensor.last_read):
        sensor.last_read, sensor.changed_ns = value, stamp_ns
    sender = sensor.sender
    if sender is not None and sender.refused_since_sense:
        sender.refused_since_sense = False
        sensor.cache.forget()  # the last frame was refused: this one is not "unchanged"
    if sensor.cache.holding and sensor.output.latest_undeliverable():
        # the last value sent can never arrive (it expired unacknowledged): the CEDDP still
        # holds the one before, so this reading must not be held back as "unchanged"
        sensor.cache.forget()
        sensor.cache_forgets += 1
    if not sensor.cache.offer(value, now_s):
        sensor.output.unchanged()
        return
    if sender is not None:
        frame = value if isinstance(value, bytes) else _message_bytes(sensor, value)
        sender.offer(writer, frame, stamp_ns, sensor.changed_ns, sensor.changed_ns)
        return
    unacked = sensor.unacked
    acked = sensor.output.acknowledged_through()
    if acked is not None:
        while unacked and unacked[0][0] <= acked:
            unacked.popleft()
    since_ns = unacked[0][1] if unacked else sensor.changed_ns
    seq = sensor.seq + 1
    if sensor.types is not None:
        raw = msgspec.Raw(_message_bytes(sensor, value))
        payload = encode(MessageSample(writer, seq, stamp_ns, raw, sensor.changed_ns, since_ns))
    elif isinstance(value, bytes):
        payload = encode(LargeSample(writer, seq, stamp_ns, value, sensor.changed_ns, since_ns))
    else:
        payload = encode(Sample(writer, seq, stamp_ns, value, sensor.changed_ns, since_ns))  # type: ignore[arg-type]
    if sensor.output.send(payload, stamp_ns):
        sensor.seq = seq
        sensor.bytes_sent += len(payload)
        if acked is not None:
            unacked.append((seq, sensor.changed_ns))
    else:
        sensor.cache.forget()


def _message_bytes(sensor: SensorChannel, message: object) -> bytes:
    assert sensor.types is not None and isinstance(message, msgspec.Struct)
    return sensor.types.encode(message)


def _driver_error(sensor: SensorChannel, writer: str, cause: str, text: str) -> None:
    text = text[:ERROR_TEXT_CHARS]
    sensor.last_driver_error = text
    throttled.log(
        logging.ERROR,
        f"{writer} {sensor.config.name} {cause}",
        "sensor %s: driver error #%d: %s",
        sensor.config.name,
        sensor.driver_errors,
        text,
    )
