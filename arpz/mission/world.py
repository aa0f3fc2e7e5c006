"""The 2-D world: walls and static obstacles as line segments, the robots' homes, the mission loop.

A world comes from a small TOML (or JSON) map file; the built-in ``hallway`` is one such file in
``arpz/mission/maps/``, so the format is documented by a working example (docs/simulation.md has the
field by field description). Everything a robot can hit or see is a segment, which keeps ray
casting and collision checks to two vectorised formulas.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Literal

import msgspec
import numpy as np
import numpy.typing as npt

from arpz.core.errors import ArpzError
from arpz.core.keys import check_chunk
from arpz.mission.kinematics import Pose

FloatArray = npt.NDArray[np.float64]

Direction = Literal["clockwise", "counterclockwise"]

#: Names of the maps shipped in ``arpz/mission/maps/``.
BUILTIN_MAPS = ("hallway", "hallway_small")

# Ray-segment hits at a segment's very end count, so a ray aimed exactly at a corner is not lost
# between the two walls that meet there.
_ENDPOINT_TOLERANCE = 1e-9


class MapError(ArpzError, ValueError):
    """A map file that cannot be used; the message names the file and the field to fix."""


class _Wall(msgspec.Struct, forbid_unknown_fields=True):
    points: list[tuple[float, float]]


class _Obstacle(msgspec.Struct, forbid_unknown_fields=True):
    centre_m: tuple[float, float]
    size_m: tuple[float, float]


class _Home(msgspec.Struct, forbid_unknown_fields=True):
    x_m: float
    y_m: float
    heading_deg: float


class _Mission(msgspec.Struct, forbid_unknown_fields=True):
    leader: str
    direction: Direction = "clockwise"
    corridor_width_m: float = 4.0
    loop_centre: tuple[float, float] | None = None
    robot_radius_m: float = 0.2


class _MapFile(msgspec.Struct, forbid_unknown_fields=True):
    name: str
    mission: _Mission
    walls: list[_Wall]
    robots: dict[str, _Home]
    obstacles: list[_Obstacle] = []


@dataclass(frozen=True, eq=False)
class Obstacle:
    """An axis-aligned box the map places in the corridor (a real obstacle, unlike a phantom)."""

    centre_x_m: float
    centre_y_m: float
    width_m: float
    height_m: float

    def corners(self) -> FloatArray:
        """The closed outline (5 points), for segments and for drawing."""
        hx, hy = self.width_m / 2.0, self.height_m / 2.0
        cx, cy = self.centre_x_m, self.centre_y_m
        return np.array(
            [
                [cx - hx, cy - hy],
                [cx + hx, cy - hy],
                [cx + hx, cy + hy],
                [cx - hx, cy + hy],
                [cx - hx, cy - hy],
            ],
            dtype=np.float64,
        )


@dataclass(frozen=True, eq=False)
class World:
    """A loaded map. ``segments`` (N x 4: x0, y0, x1, y1) holds walls then obstacle edges."""

    name: str
    wall_strips: tuple[FloatArray, ...]
    obstacles: tuple[Obstacle, ...]
    segments: FloatArray
    homes: dict[str, Pose]
    leader: str
    direction: Direction
    corridor_width_m: float
    loop_centre_m: tuple[float, float]
    robot_radius_m: float

    @property
    def robots(self) -> tuple[str, ...]:
        """Robot names, leader first, then the others in the map file's order."""
        return (self.leader, *(name for name in self.homes if name != self.leader))

    @classmethod
    def builtin(cls, name: str = "hallway") -> World:
        if name not in BUILTIN_MAPS:
            raise MapError(f"no built-in map {name!r}; built-in maps: {', '.join(BUILTIN_MAPS)}")
        text = resources.files("arpz.mission").joinpath(f"maps/{name}.toml").read_text("utf-8")
        return parse_map(text, source=f"built-in map {name!r}", fmt="toml")

    @classmethod
    def load(cls, path: str | Path) -> World:
        """Load a ``.toml`` or ``.json`` map file, or a built-in map by name (``"hallway"``)."""
        if str(path) in BUILTIN_MAPS and not Path(path).exists():
            return cls.builtin(str(path))
        path = Path(path)
        if path.suffix not in (".toml", ".json"):
            raise MapError(f"{path}: a map file must end in .toml or .json")
        try:
            text = path.read_text("utf-8")
        except OSError as exc:
            raise MapError(f"{path}: cannot read the map file: {exc.strerror}") from exc
        return parse_map(text, source=str(path), fmt="toml" if path.suffix == ".toml" else "json")

    def clearance_m(self, x_m: float, y_m: float) -> float:
        """Distance from a point to the nearest wall or obstacle edge (contact at the radius)."""
        # Called for every robot at every step by both the bodies and the judge: kept to plain
        # array arithmetic on precomputed segment data.
        start_x, start_y, along_x, along_y, inv_length2 = self._segment_terms
        dx = x_m - start_x
        dy = y_m - start_y
        t = np.clip((dx * along_x + dy * along_y) * inv_length2, 0.0, 1.0)
        gap_x = dx - t * along_x
        gap_y = dy - t * along_y
        return float(np.sqrt(np.min(gap_x * gap_x + gap_y * gap_y)))

    @cached_property
    def _segment_terms(self) -> tuple[FloatArray, ...]:
        along = self.segments[:, 2:] - self.segments[:, :2]
        inv_length2 = 1.0 / np.einsum("ij,ij->i", along, along)
        return (self.segments[:, 0], self.segments[:, 1], along[:, 0], along[:, 1], inv_length2)

    def ray_ranges_m(
        self, x_m: float, y_m: float, angles_rad: FloatArray, max_range_m: float
    ) -> FloatArray:
        """Distance along each world-frame ray to the first segment hit, ``max_range_m`` if none."""
        return cast_rays(self.segments, x_m, y_m, angles_rad, max_range_m)


def parse_map(text: str, *, source: str, fmt: Literal["toml", "json"]) -> World:
    """Decode and check a map; errors say where (``source``, field path) and what to fix."""
    try:
        if fmt == "toml":
            spec = msgspec.toml.decode(text, type=_MapFile)
        else:
            spec = msgspec.convert(json.loads(text), type=_MapFile)
    except (msgspec.ValidationError, msgspec.DecodeError, json.JSONDecodeError) as exc:
        raise MapError(f"{source}: {exc}") from exc
    return _build_world(spec, source)


def _build_world(spec: _MapFile, source: str) -> World:
    def fail(message: str) -> MapError:
        return MapError(f"{source}: {message}")

    if not spec.walls:
        raise fail("no walls: add at least one [[walls]] table with points = [[x, y], ...]")
    strips: list[FloatArray] = []
    for index, wall in enumerate(spec.walls):
        points = np.array(wall.points, dtype=np.float64).reshape(-1, 2)
        if len(points) < 2:
            raise fail(f"walls[{index}].points needs at least 2 points, got {len(points)}")
        if not np.all(np.isfinite(points)):
            raise fail(f"walls[{index}].points contains a value that is not a finite number")
        if np.any(np.all(np.diff(points, axis=0) == 0.0, axis=1)):
            raise fail(f"walls[{index}].points repeats a point: a wall segment needs two ends")
        strips.append(points)
    obstacles: list[Obstacle] = []
    for index, box in enumerate(spec.obstacles):
        if not all(math.isfinite(v) for v in (*box.centre_m, *box.size_m)):
            raise fail(f"obstacles[{index}] contains a value that is not a finite number")
        if min(box.size_m) <= 0.0:
            raise fail(f"obstacles[{index}].size_m must be positive, got {list(box.size_m)}")
        obstacles.append(Obstacle(*box.centre_m, *box.size_m))
    segments = np.concatenate(
        [_strip_segments(strip) for strip in strips]
        + [_strip_segments(box.corners()) for box in obstacles]
    )

    mission = spec.mission
    if not spec.robots:
        raise fail("no robots: add a [robots.NAME] table with x_m, y_m and heading_deg")
    for name in spec.robots:
        try:
            check_chunk(name, what="robot name")
        except ValueError as exc:
            raise fail(f"robots.{name}: {exc}") from exc
    if mission.leader not in spec.robots:
        raise fail(
            f"mission.leader = {mission.leader!r} has no home: add [robots.{mission.leader}] "
            f"(robots in this map: {', '.join(spec.robots)})"
        )
    if not 0.0 < mission.robot_radius_m < mission.corridor_width_m / 2.0:
        raise fail(
            f"mission.robot_radius_m must be > 0 and < corridor_width_m / 2, "
            f"got {mission.robot_radius_m} (corridor {mission.corridor_width_m} m)"
        )
    ends = segments.reshape(-1, 2)
    middle = (ends.min(axis=0) + ends.max(axis=0)) / 2.0
    centre = mission.loop_centre or (float(middle[0]), float(middle[1]))

    homes: dict[str, Pose] = {}
    for name, home in spec.robots.items():
        if not all(math.isfinite(v) for v in (home.x_m, home.y_m, home.heading_deg)):
            raise fail(f"robots.{name} contains a value that is not a finite number")
        clearance = float(np.min(_point_segment_distances(segments, home.x_m, home.y_m)))
        if clearance <= mission.robot_radius_m:
            raise fail(
                f"robots.{name} home ({home.x_m}, {home.y_m}) is {clearance:.2f} m from a wall, "
                f"closer than robot_radius_m = {mission.robot_radius_m}: move it into the corridor"
            )
        homes[name] = Pose(home.x_m, home.y_m, math.radians(home.heading_deg))

    return World(
        name=spec.name,
        wall_strips=tuple(strips),
        obstacles=tuple(obstacles),
        segments=segments,
        homes=homes,
        leader=mission.leader,
        direction=mission.direction,
        corridor_width_m=mission.corridor_width_m,
        loop_centre_m=(float(centre[0]), float(centre[1])),
        robot_radius_m=mission.robot_radius_m,
    )


def _strip_segments(points: FloatArray) -> FloatArray:
    return np.hstack([points[:-1], points[1:]])


def _point_segment_distances(segments: FloatArray, x_m: float, y_m: float) -> FloatArray:
    start = segments[:, :2]
    along = segments[:, 2:] - start
    to_point = np.array([x_m, y_m]) - start
    length2 = np.einsum("ij,ij->i", along, along)
    t = np.clip(np.einsum("ij,ij->i", to_point, along) / length2, 0.0, 1.0)
    nearest = start + t[:, None] * along
    return np.asarray(np.hypot(nearest[:, 0] - x_m, nearest[:, 1] - y_m), dtype=np.float64)


def cast_rays(
    segments: FloatArray, x_m: float, y_m: float, angles_rad: FloatArray, max_range_m: float
) -> FloatArray:
    """Ranges along world-frame rays from (x, y): solve origin + t*d = a + u*(b - a) per pair."""
    directions = np.stack([np.cos(angles_rad), np.sin(angles_rad)], axis=-1)  # (K, 2)
    start = segments[:, :2]  # (N, 2)
    along = segments[:, 2:] - start
    to_start = start - np.array([x_m, y_m])
    # 2-D cross products; denom == 0 means the ray runs parallel to the segment and cannot hit it.
    denom = directions[:, None, 0] * along[None, :, 1] - directions[:, None, 1] * along[None, :, 0]
    t_num = to_start[:, 0] * along[:, 1] - to_start[:, 1] * along[:, 0]  # (N,)
    u_num = (
        to_start[None, :, 0] * directions[:, None, 1]
        - to_start[None, :, 1] * directions[:, None, 0]
    )
    crossing = np.abs(denom) > 1e-12
    safe_denom = np.where(crossing, denom, 1.0)
    t = t_num[None, :] / safe_denom
    u = u_num / safe_denom
    hit = crossing & (t >= 0.0) & (u >= -_ENDPOINT_TOLERANCE) & (u <= 1.0 + _ENDPOINT_TOLERANCE)
    ranges = np.where(hit, t, np.inf).min(axis=1)
    return np.asarray(np.minimum(ranges, max_range_m), dtype=np.float64)
