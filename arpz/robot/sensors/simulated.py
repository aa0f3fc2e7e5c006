"""Seeded simulated drivers for the seven sensor kinds of seed 001 Table 1, and two large ones
(a camera and a point-cloud scanner) for fleets that send camera-sized samples.

The point of the local cache is that real sensors repeat themselves, so these drivers model the
physics that makes them do so instead of emitting white noise: a reading is quantised to the
device's resolution, the scene is mostly static, and things happen in episodes (a person walks
past the LIDAR, the PIR latches high for a few seconds, a DHT11 refreshes once a second). Every
process is driven by the time passed in, so the same seed and the same read times give the same
values, at any sampling rate.
"""

from __future__ import annotations

import math
import random
from typing import Any

import numpy as np

from arpz.robot.sensors.base import SensorDriver


class Episodes:
    """A two-state continuous-time Markov process: idle for Exp(idle_mean_s), active for
    Exp(active_mean_s), alternating. ``active(now_s)`` only ever moves forward in time."""

    def __init__(self, rng: np.random.Generator, idle_mean_s: float, active_mean_s: float) -> None:
        self._rng = rng
        self._idle_mean_s = idle_mean_s
        self._active_mean_s = active_mean_s
        self._active = False
        self._next_switch_s = float(rng.exponential(idle_mean_s))
        self.started_s = 0.0

    def active(self, now_s: float) -> bool:
        while now_s >= self._next_switch_s:
            self._active = not self._active
            self.started_s = self._next_switch_s
            mean = self._active_mean_s if self._active else self._idle_mean_s
            self._next_switch_s += float(self._rng.exponential(mean))
        return self._active


class _Quantiser:
    """A reading rounded to the device's resolution ``step``, then to 6 decimals (so that one
    level is always the same float). Each level's float is computed once: ``round(x, 6)``
    formats the float as decimal digits, and was the second line of a simulated robot's
    ``sense`` (6 % of it: ``python benchmarks/profile_shares.py RAW --within sense --lines`` of
    a ``py-spy`` profile of ``benchmarks/robot_tick_cost.py --hot``, benchmarks/RESULTS.md)."""

    #: levels kept at most; beyond, each is computed again (a driver far off its range)
    MAX_LEVELS = 100_000

    def __init__(self, step: float) -> None:
        self.step = step
        self._levels: dict[int, float] = {}

    def __call__(self, value: float) -> float:
        n = round(value / self.step)
        level = self._levels.get(n)
        if level is None:
            level = round(n * self.step, 6)
            if len(self._levels) < self.MAX_LEVELS:
                self._levels[n] = level
        return level


class _Simulated(SensorDriver):
    def __init__(self, options: dict[str, Any], seed: int) -> None:
        super().__init__(options, seed)
        #: episodes and large readings (arrays)
        self.rng = np.random.default_rng(seed)
        #: each reading's scalar draws: a Python generator's is ten times cheaper than a
        #: numpy one's (25.5 against 284 ns, ``python -m timeit``; benchmarks/RESULTS.md),
        #: and a load generator reads 40 000 times a second
        self.draw = random.Random(seed)


class SimLidar(_Simulated):
    """One LIDAR beam (m, 1 cm steps) towards a wall; people walk through it now and then."""

    kind = "lidar"

    def __init__(self, options: dict[str, Any], seed: int) -> None:
        super().__init__(options, seed)
        self.wall_m = float(options.get("wall_m", 2.0 + 4.0 * self.rng.random()))
        self.passers = Episodes(self.rng, float(options.get("idle_mean_s", 8.0)), 2.5)
        self.flicker = float(options.get("flicker", 0.05))
        self.quantise = _Quantiser(0.01)

    def read(self, now_s: float) -> float:
        distance = self.wall_m
        if self.passers.active(now_s):
            # a person crossing the beam at walking speed: nearest in the middle of the episode
            phase = now_s - self.passers.started_s
            distance = min(distance, 0.8 + 0.6 * abs(math.sin(phase * 1.3)))
        if self.draw.random() < self.flicker:
            distance += 0.01 * (1 if self.draw.random() < 0.5 else -1)
        return self.quantise(distance)


class SimDht11(_Simulated):
    """DHT11 temperature (degC, 1 degree resolution, refreshed at most once a second)."""

    kind = "dht11"

    def __init__(self, options: dict[str, Any], seed: int) -> None:
        super().__init__(options, seed)
        self.base_c = float(options.get("base_c", 22.0 + 4.0 * self.rng.random()))
        self.phase = float(self.rng.random() * 2 * math.pi)
        self._last_refresh_s = -math.inf
        self._value = self.base_c

    def read(self, now_s: float) -> float:
        if now_s - self._last_refresh_s >= 1.0:
            self._last_refresh_s = now_s
            true_c = self.base_c + 1.5 * math.sin(2 * math.pi * now_s / 600 + self.phase)
            self._value = float(round(true_c + self.draw.gauss(0.0, 0.3)))
        return self._value


class SimImu(_Simulated):
    """MPU-6050 acceleration magnitude (m/s^2, 16-bit steps at +-2 g): still most of the time."""

    kind = "imu"
    LSB = 9.80665 / 16384

    def __init__(self, options: dict[str, Any], seed: int) -> None:
        super().__init__(options, seed)
        self.moving = Episodes(self.rng, float(options.get("idle_mean_s", 10.0)), 3.0)
        self.quantise = _Quantiser(self.LSB)

    def read(self, now_s: float) -> float:
        if self.moving.active(now_s):
            value = 9.80665 + self.draw.gauss(0.0, 0.8)
        else:
            value = 9.80665 + self.draw.gauss(0.0, 0.8 * self.LSB)
        return self.quantise(value)


class SimUltrasonic(_Simulated):
    """HC-SR04 distance (cm, 0.3 cm steps) to a static object; something approaches now and then."""

    kind = "ultrasonic"

    def __init__(self, options: dict[str, Any], seed: int) -> None:
        super().__init__(options, seed)
        self.object_cm = float(options.get("object_cm", 60.0 + 100.0 * self.rng.random()))
        self.approach = Episodes(self.rng, float(options.get("idle_mean_s", 12.0)), 3.0)
        self.quantise = _Quantiser(0.3)

    def read(self, now_s: float) -> float:
        distance = self.object_cm
        if self.approach.active(now_s):
            distance = max(5.0, distance - 20.0 * (now_s - self.approach.started_s))
        distance += self.draw.gauss(0.0, 0.1)
        return self.quantise(distance)


class SimFlame(_Simulated):
    """IR flame sensor: False nearly always, a flame for a few seconds on rare occasions."""

    kind = "flame"

    def __init__(self, options: dict[str, Any], seed: int) -> None:
        super().__init__(options, seed)
        self.flames = Episodes(self.rng, float(options.get("idle_mean_s", 120.0)), 5.0)

    def read(self, now_s: float) -> bool:
        return self.flames.active(now_s)


class SimPir(_Simulated):
    """HC-SR501 PIR: latches "detect" for a few seconds after motion."""

    kind = "pir"

    def __init__(self, options: dict[str, Any], seed: int) -> None:
        super().__init__(options, seed)
        self.motion = Episodes(self.rng, float(options.get("idle_mean_s", 15.0)), 2.5)

    def read(self, now_s: float) -> str:
        return "detect" if self.motion.active(now_s) else "not detect"


class SimLight(_Simulated):
    """Photosensitive module: "light" or "dark" (lights switched off now and then)."""

    kind = "light"

    def __init__(self, options: dict[str, Any], seed: int) -> None:
        super().__init__(options, seed)
        self.darkness = Episodes(self.rng, float(options.get("idle_mean_s", 60.0)), 10.0)

    def read(self, now_s: float) -> str:
        return "dark" if self.darkness.active(now_s) else "light"


def _size_option(options: dict[str, Any], name: str, default: int) -> int:
    """A large sensor's size option: an integer >= 1, else a ValueError that names it."""
    value = options.get(name, default)
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"option {name} must be an integer >= 1, got {value!r}")
    return value


class SimCamera(_Simulated):
    """An RGB camera: ``width`` x ``height`` x 3 bytes, row-major (640 x 480 by default, 921 600
    bytes). A static scene with sensor noise on one band of rows and, in episodes, an object that
    moves across it: every frame differs, as a real camera's do, so the local cache passes them
    all unless the scene is dark (``noise = 0`` and no object: identical frames are held back)."""

    kind = "camera"

    def __init__(self, options: dict[str, Any], seed: int) -> None:
        super().__init__(options, seed)
        self.width = _size_option(options, "width", 640)
        self.height = _size_option(options, "height", 480)
        self.noise = bool(options.get("noise", True))
        self.scene = self.rng.integers(0, 256, (self.height, self.width, 3), dtype=np.uint8)
        self.objects = Episodes(self.rng, float(options.get("idle_mean_s", 2.0)), 3.0)

    def read(self, now_s: float) -> bytes:
        frame = self.scene.copy()
        if self.noise:  # a band of rows with fresh noise: cheap, and every frame differs
            band = min(8, self.height)  # a frame fewer than 8 rows high is all band
            row = int(now_s * 97) % max(1, self.height - band + 1)
            frame[row : row + band] = self.rng.integers(
                0, 256, (band, self.width, 3), dtype=np.uint8
            )
        if self.objects.active(now_s):
            x = int((now_s - self.objects.started_s) * 120) % max(1, self.width - 40)
            frame[self.height // 3 : self.height // 3 + 40, x : x + 40] = (255, 0, 0)
        return frame.tobytes()


class SimPointCloud(_Simulated):
    """A 3-D scanner: ``points`` x (x, y, z) float32, little-endian (87 381 points: 1 MB). The
    walls of a room at fixed points with range noise, so every scan differs a little."""

    kind = "pointcloud"

    def __init__(self, options: dict[str, Any], seed: int) -> None:
        super().__init__(options, seed)
        self.points = _size_option(options, "points", 87_381)
        angles = self.rng.uniform(0, 2 * math.pi, self.points)
        heights = self.rng.uniform(0.0, 2.5, self.points)
        self.rays = np.stack([np.cos(angles), np.sin(angles)], axis=1).astype(np.float32)
        self.heights = heights.astype(np.float32)
        self.ranges = self.rng.uniform(2.0, 6.0, self.points).astype(np.float32)

    def read(self, now_s: float) -> bytes:
        ranges = self.ranges + self.rng.normal(0, 0.01, self.points).astype(np.float32)
        cloud = np.empty((self.points, 3), dtype="<f4")
        cloud[:, :2] = self.rays * ranges[:, None]
        cloud[:, 2] = self.heights
        return cloud.tobytes()


SIMULATED: dict[str, type[SensorDriver]] = {
    cls.kind: cls
    for cls in (
        SimLidar,
        SimDht11,
        SimImu,
        SimUltrasonic,
        SimFlame,
        SimPir,
        SimLight,
        SimCamera,
        SimPointCloud,
    )
}
