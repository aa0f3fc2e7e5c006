"""A configurator's solution (seed 002), applied live by a robot.

``python -m arpz.configure apply`` publishes a ``ConfigurationMsg`` on ``arpz/{fleet}/ceddp/config``
(a key of its own, latched like the QoS assignment). This robot applies its part without
restarting: each listed sensor topic is sampled at its rate from the next tick on, and each listed
computation it knows runs here ("robot") or is left to the CEDDP ("ceddp"). It answers every
configuration on ``robot/{robot}/config/ack`` with what it runs now and what it refused, and
re-announces its topics so the CEDDP and the configurator see the new rates.

The one computation a robot can take over today is the hallway mission's obstacle check: on a
simulated body, "robot" runs ``LocalObstacleCheck``, which stops the robot itself when its
obstacle beam reads closer than the range, without the round trip through the CEDDP. The CEDDP's
planner keeps its own check (it is the mission's judge of when to go on); "ceddp" turns the local
one off. docs/configure.md maps the paper's node kinds to arpz's processes.

Threads: the Inlet's callback only queues; one worker (``arpz-config``) applies. A rate is a
float attribute of the sensor and of its scheduler job, read by the scheduler thread at the next
tick, as the QoS assignment does (arpz/robot/agent.py ``_on_qos``).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Protocol

from arpz.channel.io import Inlet, Outlet
from arpz.core import keys
from arpz.core.config import RobotConfig
from arpz.core.messages import (
    CONFIGURATION_DECODER,
    DECODE_ERRORS,
    ConfigurationAck,
    ConfigurationMsg,
    encode,
)
from arpz.core.throttled_log import ThrottledLog
from arpz.robot.scheduler import Job
from arpz.robot.sensing import SensorChannel

if TYPE_CHECKING:
    from arpz.core.transport import Transport

log = logging.getLogger(__name__)

#: the highest rate a configuration may ask for (the scheduler's tick is not finer than 1 ms)
MAX_RATE_HZ = 1000.0
PLACES = ("robot", "ceddp")
OBSTACLE_CHECK = "obstacle_check"
#: the hallway planner's default ``obstacle_range_m`` (arpz/mission/hallway.py PlannerSettings)
OBSTACLE_RANGE_M = 1.0


class Computation(Protocol):
    """Work that can run on the robot or be left to the CEDDP."""

    def run_here(self, enabled: bool) -> None: ...


class LocalObstacleCheck:
    """The hallway mission's obstacle check on the robot: stop when a beam reads closer than
    ``range_m`` (the planner's ``obstacle_range_m``), every ``period_s`` on its own thread."""

    def __init__(
        self,
        read_ranges: Callable[[], dict[str, float]],
        stop: Callable[[], None],
        *,
        beams: Sequence[str],
        range_m: float = 1.0,
        period_s: float = 0.02,
    ) -> None:
        self._read = read_ranges
        self._stop_robot = stop
        self.beams = tuple(beams)
        self.range_m = range_m
        self.period_s = period_s
        self.stops = 0
        self.enabled = False
        self._wake = threading.Event()
        self._thread: threading.Thread | None = None
        self._closed = False

    def run_here(self, enabled: bool) -> None:
        self.enabled = enabled
        if enabled and self._thread is None:
            self._thread = threading.Thread(target=self._loop, name="arpz-obstacle", daemon=True)
            self._thread.start()

    def check(self) -> bool:
        """One check: True (and a stop) when an obstacle beam is inside the range."""
        ranges = self._read()
        if any(ranges.get(beam, math.inf) < self.range_m for beam in self.beams):
            self._stop_robot()
            self.stops += 1
            return True
        return False

    def _loop(self) -> None:
        while not self._closed:
            if self.enabled:
                self.check()
            self._wake.wait(self.period_s)

    def close(self) -> None:
        self._closed = True
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)


class ConfigurationHandler:
    """Applies ``ConfigurationMsg`` to one robot's sensors and computations, and answers."""

    def __init__(
        self,
        config: RobotConfig,
        transport: Transport,
        *,
        incarnation: str,
        sensor_jobs: list[tuple[SensorChannel, Job]],
        computations: dict[str, Computation],
        wall_ns: Callable[[], int],
        on_applied: Callable[[], None],
    ) -> None:
        self.config = config
        self.transport = transport
        self.incarnation = incarnation
        self.sensor_jobs = sensor_jobs
        self.computations = computations
        self.wall_ns = wall_ns
        self.on_applied = on_applied
        #: where each computation runs now ("ceddp" until a configuration says otherwise)
        self.placed: dict[str, str] = dict.fromkeys(computations, "ceddp")
        self.epoch = 0
        self.applied = 0
        self.refused = 0
        self.decode_errors = 0
        #: configurations that raised while being applied (logged, the worker goes on)
        self.apply_errors = 0
        self._bad = ThrottledLog(log)
        self._queue: queue.SimpleQueue[bytes | None] = queue.SimpleQueue()
        self._worker = threading.Thread(target=self._loop, name="arpz-config", daemon=True)
        self._inlet: Inlet | None = None
        self._ack_out: Outlet | None = None

    def start(self) -> None:
        cfg = self.config
        self._worker.start()
        self._ack_out = Outlet(
            self.transport, keys.config_ack_key(cfg.fleet, cfg.robot_id), cfg.profile("report")
        )
        self._inlet = Inlet(
            self.transport,
            keys.ceddp_config_key(cfg.fleet),
            cfg.profile("assignment", downlink=True),
            lambda _key, payload: self._queue.put(payload),
        )

    def close(self) -> None:
        if self._inlet is not None:
            self._inlet.close()
        self._queue.put(None)
        self._worker.join(timeout=2.0)
        if self._ack_out is not None:
            self._ack_out.close()
        for computation in self.computations.values():
            close = getattr(computation, "close", None)
            if close is not None:
                close()

    def _loop(self) -> None:
        while True:
            payload = self._queue.get()
            if payload is None:
                return
            try:
                message = CONFIGURATION_DECODER.decode(payload)
            except DECODE_ERRORS as exc:
                self.decode_errors += 1
                self._bad.warning(
                    "decode", "undecodable configuration (%d so far): %s", self.decode_errors, exc
                )
                continue
            try:
                self.apply(message)
            except Exception:  # one bad configuration must not end the worker
                self.apply_errors += 1
                self._bad.exception(
                    "apply",
                    "configuration epoch %d failed (%d so far)",
                    message.epoch,
                    self.apply_errors,
                )

    def apply(self, message: ConfigurationMsg) -> ConfigurationAck | None:
        """Apply this robot's part (None: the configuration names other robots only)."""
        mine = message.robots.get(self.config.robot_id)
        if mine is None:
            return None
        refused: list[str] = []
        by_topic = {sensor.config.name: (sensor, job) for sensor, job in self.sensor_jobs}
        for topic, rate_hz in sorted(mine.rates_hz.items()):
            found = by_topic.get(topic)
            if found is None:
                refused.append(f"{topic}: no such sensor on {self.config.robot_id}")
                continue
            if not (math.isfinite(rate_hz) and 0.0 < rate_hz <= MAX_RATE_HZ):
                refused.append(f"{topic}: rate {rate_hz} Hz is not in (0, {MAX_RATE_HZ:g}]")
                continue
            sensor, job = found
            sensor.rate_hz = rate_hz
            job.period_s = 1.0 / rate_hz  # picked up at the sensor's next tick
            qos = sensor.output.qos
            if qos is not None and qos.deadline_s > 0:
                # the writer's DEADLINE follows the period, as a QoS assignment's does
                sensor.output.retune(depth=qos.depth, deadline_s=2.0 / rate_hz)
        for name, place in sorted(mine.computations.items()):
            computation = self.computations.get(name)
            if computation is None:
                refused.append(
                    f"{name}: this robot cannot run it (known: {sorted(self.computations)})"
                )
                continue
            if place not in PLACES:
                refused.append(f"{name}: place {place!r} is not one of {PLACES}")
                continue
            computation.run_here(place == "robot")
            self.placed[name] = place
        self.epoch = message.epoch
        self.applied += 1
        self.refused += len(refused)
        for reason in refused:
            log.warning("configuration epoch %d: refused %s", message.epoch, reason)
        log.info(
            "configuration epoch %d from %s applied: %s",
            message.epoch,
            message.sender,
            ", ".join(f"{s.config.name} {s.rate_hz:g} Hz" for s, _ in self.sensor_jobs),
        )
        self.on_applied()
        ack = ConfigurationAck(
            robot=self.config.robot_id,
            incarnation=self.incarnation,
            sender=message.sender,
            epoch=message.epoch,
            stamp_ns=self.wall_ns(),
            rates_hz={s.config.name: s.rate_hz for s, _ in self.sensor_jobs},
            computations=dict(self.placed),
            refused=refused,
        )
        if self._ack_out is not None:
            self._ack_out.send(encode(ack), ack.stamp_ns)
        return ack


def robot_computations(
    ranges: Callable[[], dict[str, float]] | None, safe_stop: Callable[[], None]
) -> dict[str, Computation]:
    """What a robot can run itself: on a simulated body (``ranges`` of its beams), the obstacle
    check of the hallway mission."""
    from arpz.mission import beam_topic

    if ranges is None:
        return {}
    check = LocalObstacleCheck(ranges, safe_stop, beams=[beam_topic(0)], range_m=OBSTACLE_RANGE_M)
    return {OBSTACLE_CHECK: check}
