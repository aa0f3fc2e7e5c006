"""The mission judge: did the fleet go round the loop and home, and if not, why not.

The judge looks at the truth the planner never sees: the robots' true poses (from the telemetry
topic, or straight from the bodies offline) and the world's geometry. It reads the planner's
events only to check them (was the obstacle it stopped for really there?) and to explain a failure
(a late turn, a fleet held for stale data).
"""

from __future__ import annotations

import math
from typing import Literal

import msgspec
import numpy as np

from arpz.mission.kinematics import Pose, wrap_angle_rad
from arpz.mission.lidar import DEFAULT_MAX_RANGE_M, beam_topic
from arpz.mission.vocabulary import MissionEvent
from arpz.mission.world import FloatArray, World

Failure = Literal["collision", "timeout", "phantom_obstacle", "incomplete"]

# Path error is computed on at most this many points per path (it is a summary, not a replay).
_MAX_FOLLOWER_POINTS = 200
_MAX_LEADER_POINTS = 1000


class JudgeSettings(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    time_limit_s: float = 150.0
    #: A robot is home within this distance of its home position ...
    home_tolerance_m: float = 0.5
    #: ... after going at least this fraction of the way round the loop centre ...
    loop_fraction: float = 0.95
    #: ... and once it has stopped (speed between its last two poses below this).
    stationary_speed_m_s: float = 0.05
    #: The planner's obstacle range; a stop is a phantom if the true range exceeds it by the margin.
    obstacle_range_m: float = 1.0
    phantom_margin_m: float = 0.3
    max_range_m: float = DEFAULT_MAX_RANGE_M

    def __post_init__(self) -> None:
        if self.time_limit_s <= 0.0:
            raise ValueError(f"JudgeSettings: time_limit_s must be > 0, got {self.time_limit_s}")
        if not 0.0 < self.loop_fraction <= 1.0:
            raise ValueError(
                f"JudgeSettings: loop_fraction must be in (0, 1], got {self.loop_fraction}"
            )


class MissionResult(msgspec.Struct, frozen=True, kw_only=True):
    """The verdict; ``mission``, ``reason`` and ``duration_s`` are what ``--json`` must carry."""

    mission: Literal["success", "failure"]
    reason: str
    duration_s: float
    #: Mean and largest distance of the followers from the leader's path shifted by their home
    #: offset: how well the fleet kept its parallel lanes. None if there was no path to compare.
    path_error_m: float | None
    path_error_max_m: float | None
    failure: Failure | None = None
    robot: str | None = None
    where_m: tuple[float, float] | None = None
    #: Fraction of the loop each robot went round (1.0 = a full loop), from the true poses.
    progress: dict[str, float] = {}


class _Track:
    """One robot's true path and how far it has wound round the loop centre."""

    def __init__(self, home: Pose, centre: tuple[float, float], sense: float) -> None:
        self.home = home
        self.centre = centre
        self.sense = sense  # +1 counter-clockwise, -1 clockwise
        self.samples: list[tuple[float, float, float, float]] = []
        self.winding_rad = 0.0
        self._bearing_rad: float | None = None

    @property
    def last(self) -> tuple[float, float, float, float] | None:
        return self.samples[-1] if self.samples else None

    @property
    def progress(self) -> float:
        return self.sense * self.winding_rad / math.tau

    def add(self, t_s: float, pose: Pose) -> None:
        bearing = math.atan2(pose.y_m - self.centre[1], pose.x_m - self.centre[0])
        if self._bearing_rad is not None:
            self.winding_rad += wrap_angle_rad(bearing - self._bearing_rad)
        self._bearing_rad = bearing
        self.samples.append((t_s, pose.x_m, pose.y_m, pose.theta_rad))

    def speed_m_s(self) -> float:
        if len(self.samples) < 2:
            return 0.0
        (t0, x0, y0, _), (t1, x1, y1, _) = self.samples[-2], self.samples[-1]
        return math.hypot(x1 - x0, y1 - y0) / (t1 - t0) if t1 > t0 else 0.0

    def home_distance_m(self) -> float:
        last = self.last
        if last is None:
            return math.inf
        return math.hypot(last[1] - self.home.x_m, last[2] - self.home.y_m)


class Judge:
    """Feed it poses and planner events as they come; it decides once and then keeps its verdict.

    ``on_pose``/``on_event``/``check`` return the verdict as soon as there is one (a collision, a
    phantom stop, success, or the time limit), else None; ``finish`` forces one at the end.
    """

    def __init__(
        self,
        world: World,
        settings: JudgeSettings | None = None,
        *,
        start_s: float = 0.0,
    ) -> None:
        self.world = world
        self.settings = settings if settings is not None else JudgeSettings()
        self.start_s = start_s
        sense = -1.0 if world.direction == "clockwise" else 1.0
        self._tracks = {
            robot: _Track(world.homes[robot], world.loop_centre_m, sense) for robot in world.robots
        }
        self.events: list[MissionEvent] = []
        self._result: MissionResult | None = None
        self._hold: tuple[str, float] | None = None  # (kind, since)
        self._held_s: dict[str, float] = {"stale_stop": 0.0, "obstacle_stop": 0.0}
        self._hold_count: dict[str, int] = {"stale_stop": 0, "obstacle_stop": 0}
        self._last_stop: dict[str, MissionEvent] = {}

    @property
    def result(self) -> MissionResult | None:
        return self._result

    def progress(self) -> dict[str, float]:
        return {robot: round(track.progress, 4) for robot, track in self._tracks.items()}

    def paths(self) -> dict[str, FloatArray]:
        """Per robot, rows of (t_s, x_m, y_m, theta_rad) of every pose judged."""
        return {
            robot: np.array(track.samples, dtype=np.float64).reshape(-1, 4)
            for robot, track in self._tracks.items()
        }

    def on_pose(self, robot: str, t_s: float, pose: Pose) -> MissionResult | None:
        track = self._tracks.get(robot)
        if track is None:
            return self._result
        track.add(t_s, pose)
        if self._result is not None:
            return self._result
        radius_m = self.world.robot_radius_m
        if self.world.clearance_m(pose.x_m, pose.y_m) <= radius_m:
            return self._decide(
                t_s, "collision", f"{robot} touched a wall at ({pose.x_m:.2f}, {pose.y_m:.2f})"
                f" at t={t_s - self.start_s:.1f} s{self._turn_context()}",
                robot=robot, where_m=(pose.x_m, pose.y_m),
            )  # fmt: skip
        for other, other_track in self._tracks.items():
            last = other_track.last
            if other == robot or last is None:
                continue
            if math.hypot(last[1] - pose.x_m, last[2] - pose.y_m) < 2.0 * radius_m:
                return self._decide(
                    t_s, "collision", f"{robot} and {other} collided at "
                    f"({pose.x_m:.2f}, {pose.y_m:.2f}) at t={t_s - self.start_s:.1f} s",
                    robot=robot, where_m=(pose.x_m, pose.y_m),
                )  # fmt: skip
        if self._all_home():
            return self._decide(t_s, None, "all robots went round the loop and stopped at home")
        return self.check(t_s)

    def on_event(self, event: MissionEvent) -> MissionResult | None:
        self.events.append(event)
        if event.kind in ("stale_stop", "obstacle_stop"):
            self._last_stop[event.kind] = event
            if self._hold is None or self._hold[0] != event.kind:
                # A repeated stale_stop while already held only updates the culprit.
                self._close_hold(event.t_s)
                self._hold = (event.kind, event.t_s)
                self._hold_count[event.kind] += 1
        elif event.kind in ("resumed", "clear"):
            self._close_hold(event.t_s)
        if self._result is None and event.kind == "obstacle_stop":
            phantom = self._phantom(event)
            if phantom is not None:
                return phantom
        return self._result

    def check(self, now_s: float) -> MissionResult | None:
        """The timeout verdict once the time limit has passed (else the verdict so far, or None)."""
        if self._result is None and now_s - self.start_s >= self.settings.time_limit_s:
            return self._timeout(now_s)
        return self._result

    def finish(self, now_s: float) -> MissionResult:
        """The verdict at the end of a run; a run ended before its time limit is "incomplete"."""
        result = self.check(now_s)
        if result is not None:
            return result
        return self._decide(
            now_s, "incomplete", f"run ended after {now_s - self.start_s:.1f} s before all robots "
            f"were home ({self._progress_text()}){self._hold_context(now_s)}",
        )  # fmt: skip

    def _all_home(self) -> bool:
        s = self.settings
        return all(
            track.progress >= s.loop_fraction
            and track.home_distance_m() <= s.home_tolerance_m
            and track.speed_m_s() <= s.stationary_speed_m_s
            for track in self._tracks.values()
        )

    def _phantom(self, event: MissionEvent) -> MissionResult | None:
        true_m = self._true_range_m(event)
        if (
            true_m is None
            or true_m <= self.settings.obstacle_range_m + self.settings.phantom_margin_m
        ):
            return None
        assert event.beam_deg is not None
        last = self._tracks[event.robot].last
        assert last is not None
        x_m, y_m = last[1], last[2]
        read = "" if event.range_m is None else f" read {event.range_m:.2f} m"
        return self._decide(
            event.t_s, "phantom_obstacle",
            f"{event.robot} was stopped for an obstacle that is not there: at "
            f"t={event.t_s - self.start_s:.1f} s its {beam_topic(event.beam_deg)}{read} but the "
            f"true range was {true_m:.2f} m "
            f"(nothing within {self.settings.obstacle_range_m:.2f} m)",
            robot=event.robot, where_m=(x_m, y_m),
        )  # fmt: skip

    def _timeout(self, now_s: float) -> MissionResult:
        return self._decide(
            now_s, "timeout", f"not all robots home within {self.settings.time_limit_s:.0f} s "
            f"({self._progress_text()}){self._hold_context(now_s)}{self._turn_context()}",
        )  # fmt: skip

    def _progress_text(self) -> str:
        """Each robot's share of the loop, and how far from home one that went round is."""
        s = self.settings

        def where(track: _Track) -> str:
            if track.progress < s.loop_fraction:
                return ""
            distance_m = track.home_distance_m()
            return f" ({distance_m:.2f} m from home)" if distance_m > s.home_tolerance_m else ""

        return "loop done: " + ", ".join(
            f"{robot} {max(round(100.0 * track.progress), 0)}%{where(track)}"
            for robot, track in self._tracks.items()
        )

    def _close_hold(self, now_s: float) -> None:
        if self._hold is not None:
            kind, since_s = self._hold
            self._held_s[kind] += max(0.0, now_s - since_s)
            self._hold = None

    def _hold_context(self, now_s: float) -> str:
        """Why the fleet was not moving: the planner's holds, as a share of the run."""
        self._close_hold(now_s)
        elapsed_s = max(now_s - self.start_s, 1e-9)
        parts = []
        for kind, what in (("stale_stop", "stale data"), ("obstacle_stop", "an obstacle")):
            share = 100.0 * self._held_s[kind] / elapsed_s
            if share < 1.0:
                continue  # the wait for the first readings is not a reason
            last = self._last_stop[kind]
            stops = self._hold_count[kind]
            truth = self._true_range_text(last) if kind == "obstacle_stop" else ""
            parts.append(
                f"the planner held the fleet for {what} {share:.0f}% of the time "
                f"({stops} stop{'s' if stops > 1 else ''}; last: {last.text}{truth})"
            )
        home = next(
            (e for e in reversed(self.events) if e.kind == "home" and e.robot == self.world.leader),
            None,
        )
        if home is not None:
            leader = self._tracks[self.world.leader]
            if leader.home_distance_m() > self.settings.home_tolerance_m:
                parts.append(
                    f"the planner declared home at t={home.t_s - self.start_s:.1f} s "
                    f"({home.text}) with {self.world.leader} "
                    f"{leader.home_distance_m():.1f} m from its home"
                )
        return "; " + "; ".join(parts) if parts else ""

    def _true_range_text(self, event: MissionEvent) -> str:
        """What the stopping beam really saw, from the robot's latest true pose."""
        true_m = self._true_range_m(event)
        return "" if true_m is None else f"; true range now {true_m:.2f} m"

    def _true_range_m(self, event: MissionEvent) -> float | None:
        track = self._tracks.get(event.robot)
        if track is None or track.last is None or event.beam_deg is None:
            return None
        _, x_m, y_m, theta_rad = track.last
        angle = np.array([theta_rad + math.radians(event.beam_deg)])
        return float(self.world.ray_ranges_m(x_m, y_m, angle, self.settings.max_range_m)[0])

    def _turn_context(self) -> str:
        """The last corner the planner started, with the reading behind it: late turns show here."""
        for event in reversed(self.events):
            if event.kind == "turn_started":
                return (
                    f"; the last turn started at t={event.t_s - self.start_s:.1f} s: {event.text}"
                )
        return ""

    def _decide(
        self,
        t_s: float,
        failure: Failure | None,
        reason: str,
        *,
        robot: str | None = None,
        where_m: tuple[float, float] | None = None,
    ) -> MissionResult:
        mean_m, max_m = self._path_error()
        self._result = MissionResult(
            mission="success" if failure is None else "failure",
            reason=reason if failure is None else f"{failure.replace('_', ' ')}: {reason}",
            duration_s=round(t_s - self.start_s, 3),
            path_error_m=mean_m,
            path_error_max_m=max_m,
            failure=failure,
            robot=robot,
            where_m=where_m,
            progress=self.progress(),
        )
        return self._result

    def _path_error(self) -> tuple[float | None, float | None]:
        leader = self._tracks[self.world.leader]
        lead = np.array([s[1:3] for s in leader.samples], dtype=np.float64).reshape(-1, 2)
        if len(lead) < 2:
            return None, None
        lead = lead[:: max(1, len(lead) // _MAX_LEADER_POINTS)]
        errors: list[FloatArray] = []
        for robot, track in self._tracks.items():
            if robot == self.world.leader or not track.samples:
                continue
            offset = np.array([track.home.x_m - leader.home.x_m, track.home.y_m - leader.home.y_m])
            points = np.array([s[1:3] for s in track.samples], dtype=np.float64)
            points = points[:: max(1, len(points) // _MAX_FOLLOWER_POINTS)] - offset
            errors.append(_distances_to_polyline(points, lead))
        if not errors:
            return None, None
        all_errors = np.concatenate(errors)
        return round(float(all_errors.mean()), 4), round(float(all_errors.max()), 4)


def _distances_to_polyline(points: FloatArray, polyline: FloatArray) -> FloatArray:
    start = polyline[:-1]
    along = polyline[1:] - start
    length2 = np.einsum("ij,ij->i", along, along)
    rel = points[:, None, :] - start[None, :, :]
    # A stationary leader repeats points: a zero-length segment is just its start point.
    safe_length2 = np.where(length2 > 0.0, length2, 1.0)
    t = np.clip(np.einsum("mkj,kj->mk", rel, along) / safe_length2, 0.0, 1.0)
    gap = rel - t[:, :, None] * along[None, :, :]
    return np.asarray(np.sqrt(np.einsum("mkj,mkj->mk", gap, gap)).min(axis=1), dtype=np.float64)
