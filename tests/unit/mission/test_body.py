import math

import pytest

from arpz.mission.body import RobotBody
from arpz.mission.kinematics import Pose
from arpz.mission.world import World

HALLWAY = World.builtin()


def test_body_starts_at_its_home_and_drives_the_latest_command() -> None:
    body = RobotBody(HALLWAY, "robot1", command_timeout_s=None)
    assert body.pose == HALLWAY.homes["robot1"]
    body.step(1.0)
    assert body.pose == HALLWAY.homes["robot1"]  # no command yet: it stays put
    body.apply_command(0.5, 0.0)
    body.step(2.0)
    assert body.pose == pytest.approx(Pose(9.0, 2.0, math.pi))  # heading west: 1 m along -x
    assert body.t_s == pytest.approx(3.0)


def test_commands_are_clipped_to_the_body_limits() -> None:
    body = RobotBody(HALLWAY, "robot1", max_speed_m_s=1.0, max_omega_rad_s=2.0)
    body.apply_command(5.0, -9.0)
    assert body.command == (1.0, -2.0)
    body.apply_command(float("nan"), 1.0)
    assert body.command == (0.0, 0.0)


def test_watchdog_stops_a_body_that_hears_nothing_for_the_timeout() -> None:
    body = RobotBody(HALLWAY, "robot1", command_timeout_s=0.5)
    body.apply_command(1.0, 0.0)
    body.step(2.0)  # one late step: the watchdog cuts in inside it, after 0.5 s
    assert body.pose.x_m == pytest.approx(9.5)
    assert body.command == (0.0, 0.0)


def test_a_paused_body_does_not_move_and_its_command_expires_meanwhile() -> None:
    body = RobotBody(HALLWAY, "robot1")  # a frozen process: time passes, the body does not move
    body.apply_command(0.5, 0.0)
    body.pause(0.4)
    assert body.pose == HALLWAY.homes["robot1"]
    body.step(0.2)  # 0.1 s of the 0.5 s timeout was left
    assert body.pose.x_m == pytest.approx(10.0 - 0.05)
    assert body.command == (0.0, 0.0)
    with pytest.raises(ValueError, match="dt_s must be >= 0"):
        body.pause(-1.0)


def test_body_stops_dead_at_the_first_contact_with_a_wall() -> None:
    body = RobotBody(HALLWAY, "robot3", command_timeout_s=None, max_substep_s=0.01)
    # robot3 sits 1 m above the outer wall, facing west; turn it to face south and drive.
    body.apply_command(0.0, math.pi / 2)
    body.step(1.0)
    body.apply_command(1.0, 0.0)
    body.step(5.0)  # one big step: sub-steps stop it at the wall instead of tunnelling through
    assert body.collided
    radius_m = HALLWAY.robot_radius_m
    assert body.pose.y_m == pytest.approx(radius_m, abs=0.011)
    assert body.pose.y_m <= radius_m
    before = body.pose
    body.step(1.0)
    assert body.pose == before


def test_scan_is_keyed_by_beam_angle() -> None:
    scan = RobotBody(HALLWAY, "robot1").scan()
    assert list(scan) == [0, 45, 90, 135, 180, 225, 270, 315]
    assert scan[90] == pytest.approx(2.0)
    readings = RobotBody(HALLWAY, "robot1").readings()
    assert list(readings) == [f"lidar_{deg}" for deg in scan]
    assert readings["lidar_0"] == pytest.approx(10.0)


def test_unknown_robot_needs_an_explicit_home() -> None:
    with pytest.raises(ValueError, match="no home in map 'hallway'"):
        RobotBody(HALLWAY, "robot9")
    assert RobotBody(HALLWAY, "robot9", home=Pose(2.0, 6.0, 0.0)).pose.y_m == 6.0
