"""Seeded simulated drivers for the seven sensor kinds of seed 001 Table 1, two large ones (a
camera and a point-cloud scanner) for fleets that send camera-sized samples, and three typed
ones (``driver = "sim"`` for ``type = "sensor_msgs/msg/LaserScan"``, ``Image`` and
``CompressedImage``: ``SIMULATED_MESSAGES``) that give whole ROS 2 messages.

The point of the local cache is that real sensors repeat themselves, so these drivers model the
physics that makes them do so instead of emitting white noise: a reading is quantised to the
device's resolution, the scene is mostly static, and things happen in episodes (a person walks
past the LIDAR, the PIR latches high for a few seconds, a DHT11 refreshes once a second). Every
process is driven by the time passed in, so the same seed and the same read times give the same
values, at any sampling rate.
"""

from __future__ import annotations

import importlib
import math
import random
from typing import Any, ClassVar

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
    ``sense`` (6 % of it: ``python benchmarks/investigations/profile_shares.py RAW --within sense
    --lines`` of
    a ``py-spy`` profile of ``benchmarks/investigations/robot_tick_cost.py --hot``,
    benchmarks/RESULTS.md)."""

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


def _noise_band(height: int, now_s: float) -> tuple[int, int]:
    """The first row and the height of a frame's band of fresh sensor noise at ``now_s``: 8
    rows moving down the frame (a frame fewer than 8 rows high is all band)."""
    band = min(8, height)
    return int(now_s * 97) % max(1, height - band + 1), band


def _moving_square(frame: np.ndarray, objects: Episodes, now_s: float) -> None:
    """In an episode of ``objects``, a red 40-pixel square moving across the frame's upper third
    at 120 pixels a second."""
    if objects.active(now_s):
        height, width = frame.shape[:2]
        x = int((now_s - objects.started_s) * 120) % max(1, width - 40)
        frame[height // 3 : height // 3 + 40, x : x + 40] = (255, 0, 0)


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
            row, band = _noise_band(self.height, now_s)
            frame[row : row + band] = self.rng.integers(
                0, 256, (band, self.width, 3), dtype=np.uint8
            )
        _moving_square(frame, self.objects, now_s)
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


class _SimulatedMessage(_Simulated):
    """A simulated typed sensor: ``read`` gives a dict of its message's fields (numpy arrays
    where the type has arrays), the header left out for the robot to stamp. Its ``options``
    are checked against ``OPTIONS``, so a misspelt one stops the robot instead of being
    ignored; ``rate_hz`` is the sensor's configured rate (a LIDAR's scan time)."""

    kind: ClassVar[str] = "message"
    #: the ROS 2 message type it gives
    ros_type: ClassVar[str] = ""
    OPTIONS: ClassVar[tuple[str, ...]] = ()

    def __init__(self, options: dict[str, Any], seed: int, *, rate_hz: float = 10.0) -> None:
        super().__init__(options, seed)
        unknown = sorted(set(options) - set(self.OPTIONS))
        if unknown:
            raise ValueError(
                f"unknown option {', '.join(unknown)}: a simulated {self.ros_type} takes "
                f"{', '.join(self.OPTIONS)}"
            )
        self.rate_hz = rate_hz


def _number_option(
    options: dict[str, Any], name: str, default: float, *, low: float, high: float = math.inf
) -> float:
    """A finite number option in [low, high], else a ValueError that names it."""
    value = options.get(name, default)
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"option {name} must be a number, got {value!r}")
    if not (math.isfinite(value) and low <= value <= high):
        bound = f"from {low:g} to {high:g}" if math.isfinite(high) else f">= {low:g}"
        raise ValueError(f"option {name} must be a finite number {bound}, got {value!r}")
    return float(value)


class SimLaserScan(_SimulatedMessage):
    """A 2-D LIDAR in a rectangular room: a ``sensor_msgs/msg/LaserScan`` of ``beams`` ranges
    over ``fov_deg`` centred straight ahead (angle 0), from ``angle_min = -fov/2``; over a full
    turn the beams are ``fov/beams`` apart (the last one a step short of the first), over less
    than a turn ``fov/(beams - 1)`` (the first and last on the field's edges, as a Hokuyo's
    270-degree 1081-beam scan). The scanner spins once per period of the sensor's rate
    (``scan_time = 1/rate_hz``, ``time_increment`` the time between two beams).

    The room (``room_m = [width, depth]``, seeded 4-8 m by 3-6 m) holds the robot at a seeded
    pose at least 0.5 m from its walls; every range gets Gaussian noise (``noise_m``, 1 cm) in
    millimetre steps, so every scan differs a little as a real one does (``noise_m = 0``: the
    same scan until someone walks by, which the local cache holds back). In episodes (about
    every ``idle_mean_s`` = 8 s) a person, a disc of 0.25 m radius, walks across the room 1 m
    from the robot. A range beyond ``range_max`` reads +inf and one under ``range_min`` -inf
    (REP 117); ``intensities = true`` fills the intensities (stronger for nearer returns, 0 for
    none), which are left empty by default."""

    ros_type = "sensor_msgs/msg/LaserScan"
    OPTIONS = (
        "beams",
        "fov_deg",
        "range_min",
        "range_max",
        "noise_m",
        "room_m",
        "intensities",
        "idle_mean_s",
    )
    PERSON_RADIUS_M = 0.25
    WALK_M_S = 1.2

    def __init__(self, options: dict[str, Any], seed: int, *, rate_hz: float = 10.0) -> None:
        super().__init__(options, seed, rate_hz=rate_hz)
        self.beams = _size_option(options, "beams", 360)
        fov = math.radians(_number_option(options, "fov_deg", 360.0, low=1e-3, high=360.0))
        full_turn = math.isclose(fov, 2 * math.pi)
        if not full_turn and self.beams < 2:
            raise ValueError("option beams must be >= 2 for a field of view under 360 degrees")
        self.range_min = _number_option(options, "range_min", 0.12, low=0.0)
        self.range_max = _number_option(options, "range_max", 12.0, low=self.range_min)
        if self.range_max <= self.range_min:
            raise ValueError(
                f"option range_max ({self.range_max:g}) must be above range_min "
                f"({self.range_min:g})"
            )
        self.noise_m = _number_option(options, "noise_m", 0.01, low=0.0)
        self.with_intensities = bool(options.get("intensities", False))
        room = options.get("room_m", [4.0 + 4.0 * self.rng.random(), 3.0 + 3.0 * self.rng.random()])
        if not (isinstance(room, list | tuple) and len(room) == 2):
            raise ValueError(f"option room_m must be [width, depth] in metres, got {room!r}")
        width, depth = (_number_option({"room_m": side}, "room_m", 0.0, low=1.0) for side in room)
        increment = fov / self.beams if full_turn else fov / (self.beams - 1)
        angle_min = -fov / 2
        angles = angle_min + increment * np.arange(self.beams)
        # the robot's pose in the room, at least 0.5 m from every wall
        x = 0.5 + (width - 1.0) * self.rng.random()
        y = 0.5 + (depth - 1.0) * self.rng.random()
        heading = 2 * math.pi * self.rng.random()
        self.origin = np.array([x, y])
        self.rays = np.stack([np.cos(angles + heading), np.sin(angles + heading)], axis=1)
        self.walls = _ranges_in_box(self.origin, self.rays, width, depth)
        self.room_width = width
        # a person walks along the room's width, 1 m to one side of the robot (inside the room)
        side = 1.0 if y + 1.0 < depth else -1.0
        self.walk_y = y + side
        self.walkers = Episodes(
            self.rng, float(options.get("idle_mean_s", 8.0)), width / self.WALK_M_S
        )
        scan_time = 1.0 / rate_hz
        self.fields: dict[str, Any] = {
            "angle_min": angle_min,
            "angle_max": angle_min + increment * (self.beams - 1),
            "angle_increment": increment,
            "time_increment": scan_time * increment / (2 * math.pi),
            "scan_time": scan_time,
            "range_min": self.range_min,
            "range_max": self.range_max,
        }

    def read(self, now_s: float) -> dict[str, Any]:
        ranges = self.walls
        if self.walkers.active(now_s):
            walked = (now_s - self.walkers.started_s) * self.WALK_M_S
            person = np.array([walked, self.walk_y])
            ranges = np.minimum(
                ranges, _ranges_to_disc(self.origin, self.rays, person, self.PERSON_RADIUS_M)
            )
        if self.noise_m > 0:
            ranges = ranges + self.rng.normal(0.0, self.noise_m, self.beams)
        ranges = np.round(ranges, 3)
        intensities: Any = []
        if self.with_intensities:
            intensities = np.clip(100.0 - 6.0 * ranges, 10.0, 100.0)
            intensities[ranges > self.range_max] = 0.0
        ranges[ranges > self.range_max] = math.inf
        ranges[ranges < self.range_min] = -math.inf
        return {**self.fields, "ranges": ranges, "intensities": intensities}


def _ranges_in_box(origin: np.ndarray, rays: np.ndarray, width: float, depth: float) -> np.ndarray:
    """The distance along each ray from ``origin`` (inside [0, width] x [0, depth]) to the box's
    walls."""
    with np.errstate(divide="ignore"):
        far = np.where(rays > 0, np.array([width, depth]) - origin, -origin) / rays
    far[~np.isfinite(far) | (far < 0)] = math.inf  # a ray parallel to a wall never meets it
    return np.asarray(far.min(axis=1))


def _ranges_to_disc(
    origin: np.ndarray, rays: np.ndarray, centre: np.ndarray, radius: float
) -> np.ndarray:
    """The distance along each (unit) ray from ``origin`` to a disc, inf for a ray that misses."""
    to_centre = centre - origin
    along = rays @ to_centre
    gap2 = float(to_centre @ to_centre) - radius * radius
    disc = along * along - gap2
    hit = (disc >= 0) & (along > 0)
    ranges = np.full(len(rays), math.inf)
    ranges[hit] = along[hit] - np.sqrt(disc[hit])
    return ranges


class _SimulatedFrames(_SimulatedMessage):
    """``width`` x ``height`` RGB frames of a seeded scene shaped like a real one (gradients, the
    edges of vertical bars and fixed sensor noise: what a JPEG encoder meets, where random
    pixels would not compress at all), with a band of fresh noise moving down every frame and,
    in episodes (about every ``idle_mean_s`` = 2 s), a red square moving across: every frame
    differs (``noise = false`` and no square: the same frame, which the local cache holds
    back)."""

    OPTIONS: ClassVar[tuple[str, ...]] = ("width", "height", "noise", "idle_mean_s")

    def __init__(self, options: dict[str, Any], seed: int, *, rate_hz: float = 10.0) -> None:
        super().__init__(options, seed, rate_hz=rate_hz)
        self.width = _size_option(options, "width", 640)
        self.height = _size_option(options, "height", 480)
        self.noise = bool(options.get("noise", True))
        self.scene = _scene(self.rng, self.width, self.height)
        self.objects = Episodes(self.rng, float(options.get("idle_mean_s", 2.0)), 3.0)

    def frame(self, now_s: float) -> np.ndarray:
        frame = self.scene.copy()
        if self.noise:
            row, band = _noise_band(self.height, now_s)
            noise = self.rng.integers(-12, 13, (band, self.width, 3), dtype=np.int16)
            frame[row : row + band] = np.clip(frame[row : row + band] + noise, 0, 255)
        _moving_square(frame, self.objects, now_s)
        return frame


def _scene(rng: np.random.Generator, width: int, height: int) -> np.ndarray:
    """A seeded RGB scene: colour gradients, vertical bars of half brightness, sensor noise."""
    y, x = np.mgrid[0:height, 0:width]
    phase = int(rng.integers(0, 80))
    scene = np.stack(
        [x * 255 // width, y * 255 // height, (x + y) * 255 // (width + height)], axis=-1
    )
    scene[((x + phase) // 80) % 2 == 0] //= 2
    noise = rng.normal(0.0, 6.0, scene.shape)
    return np.asarray(np.clip(scene + noise, 0, 255), dtype=np.uint8)


class SimImage(_SimulatedFrames):
    """A camera's raw ``sensor_msgs/msg/Image``: ``rgb8``, ``width`` x ``height`` (640 x 480 by
    default: 921 600 bytes of data), ``step = 3 * width``; the frames of ``_SimulatedFrames``."""

    ros_type = "sensor_msgs/msg/Image"

    def read(self, now_s: float) -> dict[str, Any]:
        return {
            "height": self.height,
            "width": self.width,
            "encoding": "rgb8",
            "is_bigendian": 0,
            "step": 3 * self.width,
            "data": self.frame(now_s),
        }


#: what a CompressedImage sim sensor needs beyond arpz's own dependencies
JPEG_EXTRA = "pip install 'arpz[jpeg]'"


class SimCompressedImage(_SimulatedFrames):
    """A camera's ``sensor_msgs/msg/CompressedImage``: the frames of ``_SimulatedFrames`` as JPEG
    (``format = "jpeg"``) at ``quality`` (1-100, 80 by default) with 4:2:0 chroma subsampling,
    encoded by simplejpeg (libjpeg-turbo; the fastest of four encoders in
    ``benchmarks/image_encoders.py``): the ``jpeg`` extra, ``pip install 'arpz[jpeg]'``."""

    ros_type = "sensor_msgs/msg/CompressedImage"
    OPTIONS = (*_SimulatedFrames.OPTIONS, "quality")

    def __init__(self, options: dict[str, Any], seed: int, *, rate_hz: float = 10.0) -> None:
        super().__init__(options, seed, rate_hz=rate_hz)
        quality = options.get("quality", 80)
        if isinstance(quality, bool) or not isinstance(quality, int) or not 1 <= quality <= 100:
            raise ValueError(f"option quality must be an integer from 1 to 100, got {quality!r}")
        self.quality = quality
        try:
            self._jpeg: Any = importlib.import_module("simplejpeg")
        except ImportError:
            raise ValueError(
                "a simulated CompressedImage encodes JPEG with simplejpeg, which is not "
                f"installed: {JPEG_EXTRA}"
            ) from None

    def read(self, now_s: float) -> dict[str, Any]:
        data = self._jpeg.encode_jpeg(
            self.frame(now_s), quality=self.quality, colorspace="RGB", colorsubsampling="420"
        )
        return {"format": "jpeg", "data": data}


#: the typed simulated drivers by the ROS 2 type they give (``driver = "sim"`` with ``type``;
#: arpz.core.config.SIMULATED_TYPES names the same types, for the config's check)
SIMULATED_MESSAGES: dict[str, type[_SimulatedMessage]] = {
    cls.ros_type: cls for cls in (SimLaserScan, SimImage, SimCompressedImage)
}


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
