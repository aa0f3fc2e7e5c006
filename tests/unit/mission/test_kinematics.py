import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from arpz.mission.kinematics import Pose, integrate, wrap_angle_rad


def test_straight_line_moves_v_times_dt_along_the_heading() -> None:
    pose = integrate(Pose(1.0, 2.0, math.pi / 2), 0.5, 0.0, 4.0)
    assert pose == pytest.approx(Pose(1.0, 4.0, math.pi / 2))


def test_turn_in_place_changes_only_the_heading() -> None:
    pose = integrate(Pose(3.0, 4.0, 0.0), 0.0, 0.5, math.pi)  # half a radian/s for pi s
    assert pose == pytest.approx(Pose(3.0, 4.0, math.pi / 2))


def test_quarter_arc_has_radius_v_over_omega() -> None:
    # v = 1 m/s, omega = 0.5 rad/s: radius 2 m, centre at (0, 2) on the left; a quarter turn takes
    # pi s and ends at (2, 2) heading +y.
    pose = integrate(Pose(0.0, 0.0, 0.0), 1.0, 0.5, math.pi)
    assert pose == pytest.approx(Pose(2.0, 2.0, math.pi / 2))


def test_right_turn_arc_goes_clockwise() -> None:
    pose = integrate(Pose(0.0, 0.0, 0.0), 1.0, -1.0, math.pi / 2)  # radius 1, centre (0, -1)
    assert pose == pytest.approx(Pose(1.0, -1.0, -math.pi / 2))


def test_negative_dt_is_refused() -> None:
    with pytest.raises(ValueError, match="dt_s"):
        integrate(Pose(0.0, 0.0, 0.0), 1.0, 0.0, -0.1)


def test_wrap_angle_maps_into_minus_pi_pi() -> None:
    assert wrap_angle_rad(3 * math.pi / 2) == pytest.approx(-math.pi / 2)
    assert wrap_angle_rad(-math.pi) == pytest.approx(math.pi)


speeds = st.floats(-1.0, 1.0)
rates = st.floats(-2.0, 2.0)


@given(speeds, rates, st.floats(0.0, 5.0), st.integers(2, 20))
def test_integration_does_not_depend_on_the_step_size(
    v_m_s: float, omega_rad_s: float, dt_s: float, pieces: int
) -> None:
    whole = integrate(Pose(1.0, -2.0, 0.3), v_m_s, omega_rad_s, dt_s)
    split = Pose(1.0, -2.0, 0.3)
    for _ in range(pieces):
        split = integrate(split, v_m_s, omega_rad_s, dt_s / pieces)
    assert split.x_m == pytest.approx(whole.x_m, abs=1e-6)
    assert split.y_m == pytest.approx(whole.y_m, abs=1e-6)
    assert wrap_angle_rad(split.theta_rad - whole.theta_rad) == pytest.approx(0.0, abs=1e-6)


@given(st.floats(0.1, 1.0), st.floats(0.1, 2.0), st.floats(0.0, 10.0))
def test_arc_stays_at_radius_from_its_centre(v_m_s: float, omega_rad_s: float, dt_s: float) -> None:
    radius_m = v_m_s / omega_rad_s
    pose = integrate(Pose(0.0, 0.0, 0.0), v_m_s, omega_rad_s, dt_s)
    assert math.hypot(pose.x_m, pose.y_m - radius_m) == pytest.approx(radius_m, rel=1e-9)
