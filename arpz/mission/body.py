"""One simulated robot body: kinematics driven by the latest command, LIDAR, contact with walls.

This is what a robot process runs in place of Gazebo. It holds no network code: the robot agent
feeds it commands as they arrive from actuation, steps it by the simulated clock, publishes its
beams through the local cache like any sensor and its true pose on the telemetry topic.
"""

from __future__ import annotations

import math

from arpz.mission.kinematics import Pose, integrate
from arpz.mission.lidar import DEFAULT_MAX_RANGE_M, Lidar
from arpz.mission.world import World


class RobotBody:
    """A differential-drive disc of the world's robot radius that stops dead when it touches a wall.

    Commands are clipped to the body's limits and expire after ``command_timeout_s`` (a motor
    watchdog, as on a real base): a robot that stops hearing from the CEDDP stops instead of
    driving on blind with its last command.
    """

    def __init__(
        self,
        world: World,
        name: str,
        *,
        home: Pose | None = None,
        lidar: Lidar | None = None,
        max_speed_m_s: float = 1.0,
        max_omega_rad_s: float = 2.0,
        command_timeout_s: float | None = 0.5,
        max_substep_s: float = 0.02,
    ) -> None:
        if home is None:
            if name not in world.homes:
                raise ValueError(
                    f"robot {name!r} has no home in map {world.name!r} "
                    f"(robots: {', '.join(world.homes)}); pass home=Pose(...)"
                )
            home = world.homes[name]
        self.world = world
        self.name = name
        self.lidar = lidar if lidar is not None else Lidar(world, max_range_m=DEFAULT_MAX_RANGE_M)
        self.max_speed_m_s = max_speed_m_s
        self.max_omega_rad_s = max_omega_rad_s
        self.command_timeout_s = command_timeout_s
        self.max_substep_s = max_substep_s
        self._pose = home
        self._t_s = 0.0
        self._v_m_s = 0.0
        self._omega_rad_s = 0.0
        self._command_t_s = -math.inf
        self._collided = False

    @property
    def pose(self) -> Pose:
        """The true pose: for the telemetry topic (judge, drawing), never for the planner."""
        return self._pose

    @property
    def t_s(self) -> float:
        """Simulated seconds this body has been stepped for."""
        return self._t_s

    @property
    def collided(self) -> bool:
        return self._collided

    @property
    def command(self) -> tuple[float, float]:
        """The (v_m_s, omega_rad_s) in force now, after clipping and the watchdog."""
        if self._command_expired():
            return (0.0, 0.0)
        return (self._v_m_s, self._omega_rad_s)

    def apply_command(self, v_m_s: float, omega_rad_s: float) -> None:
        """Take a velocity command from actuation; it holds until replaced or timed out."""
        if not (math.isfinite(v_m_s) and math.isfinite(omega_rad_s)):
            v_m_s, omega_rad_s = 0.0, 0.0
        self._v_m_s = min(max(v_m_s, -self.max_speed_m_s), self.max_speed_m_s)
        self._omega_rad_s = min(max(omega_rad_s, -self.max_omega_rad_s), self.max_omega_rad_s)
        self._command_t_s = self._t_s

    def step(self, dt_s: float) -> Pose:
        """Advance ``dt_s`` in sub-steps, so a late loop cannot jump the body through a wall."""
        if dt_s < 0.0:
            raise ValueError(f"dt_s must be >= 0, got {dt_s}")
        remaining_s = dt_s
        while remaining_s > 1e-12:
            sub_s = min(remaining_s, self.max_substep_s)
            if self.command_timeout_s is not None:
                # The watchdog fires inside this step, not only at its end.
                left_s = self._command_t_s + self.command_timeout_s - self._t_s
                if left_s > 1e-12:
                    sub_s = min(sub_s, left_s)
            v_m_s, omega_rad_s = self.command
            if not self._collided and (v_m_s or omega_rad_s):
                pose = integrate(self._pose, v_m_s, omega_rad_s, sub_s)
                if self.world.clearance_m(pose.x_m, pose.y_m) <= self.world.robot_radius_m:
                    self._collided = True
                self._pose = pose
            self._t_s += sub_s
            remaining_s -= sub_s
        return self._pose

    def pause(self, dt_s: float) -> None:
        """Let ``dt_s`` pass without moving, as for a robot whose process is stopped: the time
        counts towards the command timeout, so the body does not drive on when it wakes up."""
        if dt_s < 0.0:
            raise ValueError(f"dt_s must be >= 0, got {dt_s}")
        self._t_s += dt_s

    def scan(self) -> dict[int, float]:
        """One LIDAR reading per beam angle (degrees) from the true pose."""
        ranges = self.lidar.scan(self._pose)
        return {deg: float(r) for deg, r in zip(self.lidar.beams_deg, ranges, strict=True)}

    def readings(self) -> dict[str, float]:
        """One scan as ``{"lidar_0": range_m, ...}``: the values to publish on the beam topics."""
        return self.lidar.readings(self._pose)

    def _command_expired(self) -> bool:
        return (
            self.command_timeout_s is not None
            and self._t_s - self._command_t_s >= self.command_timeout_s - 1e-12
        )
