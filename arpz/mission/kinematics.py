"""Differential-drive kinematics: the body model every simulated robot shares.

Integration is exact for a constant command (a straight line or a circular arc), so the pose does
not drift with the step size: a robot process stepping at an irregular wall-clock rate ends up
where an offline run stepping at a fixed rate does.
"""

from __future__ import annotations

import math
from typing import NamedTuple


class Pose(NamedTuple):
    """Where a robot is in the world frame (x right, y up, heading counter-clockwise from +x)."""

    x_m: float
    y_m: float
    theta_rad: float


def wrap_angle_rad(angle_rad: float) -> float:
    """The same direction in (-pi, pi], so that heading differences stay small numbers."""
    wrapped = math.remainder(angle_rad, math.tau)
    return math.pi if wrapped == -math.pi else wrapped


def integrate(pose: Pose, v_m_s: float, omega_rad_s: float, dt_s: float) -> Pose:
    """Move ``pose`` for ``dt_s`` under a constant forward speed and turn rate.

    A turn with ``omega_rad_s != 0`` follows an arc of radius ``v_m_s / omega_rad_s`` about a
    centre on the robot's left (omega > 0) or right (omega < 0); with ``v_m_s == 0`` the robot
    turns in place.
    """
    if dt_s < 0.0:
        raise ValueError(f"dt_s must be >= 0, got {dt_s}")
    x, y, theta = pose
    dtheta = omega_rad_s * dt_s
    if abs(dtheta) < 1e-9:
        # Straight line (or a turn too small for the arc formula's division to be accurate).
        mid = theta + 0.5 * dtheta
        return Pose(
            x + v_m_s * dt_s * math.cos(mid),
            y + v_m_s * dt_s * math.sin(mid),
            wrap_angle_rad(theta + dtheta),
        )
    radius_m = v_m_s / omega_rad_s
    new_theta = theta + dtheta
    return Pose(
        x + radius_m * (math.sin(new_theta) - math.sin(theta)),
        y - radius_m * (math.cos(new_theta) - math.cos(theta)),
        wrap_angle_rad(new_theta),
    )
