"""The closed loop without a network: the hallway mission end to end on simulated time."""

from importlib import resources

import pytest

from arpz.mission.hallway import PlannerSettings
from arpz.mission.offline import run_offline
from arpz.mission.world import World, parse_map

HALLWAY = World.builtin()
SETTINGS = PlannerSettings.for_world(HALLWAY)
# The leader's loop: 48 m of centreline, less 4 x (2 m - a quarter of a 1 m circle) at the corners.
LOOP_M = 48.0 - 4 * (2.0 - 3.14159265 / 2)


def test_default_rate_goes_round_and_home_in_parallel_lanes() -> None:
    run = run_offline(HALLWAY, SETTINGS, beam_rate_hz=20.0, duration_s=120.0, noise_std_m=0.01)
    result = run.result
    assert result.mission == "success", result.reason
    # At 0.8 m/s plus the wait for the first readings and a tick of slack at each end.
    assert result.duration_s == pytest.approx(LOOP_M / 0.8, abs=0.5)
    assert [e.corner for e in run.events if e.kind == "turn_done"] == [1, 2, 3, 4]
    assert run.events[-1].kind == "home"
    # Same commands at the same moments: each follower's path is the leader's, shifted.
    assert result.path_error_max_m is not None and result.path_error_max_m < 0.01
    for robot, path in run.paths.items():
        home = HALLWAY.homes[robot]
        assert path[-1, 1:3] == pytest.approx([home.x_m, home.y_m], abs=0.2)


def test_one_hz_lidar_fails_on_stale_data_and_says_so() -> None:
    run = run_offline(HALLWAY, SETTINGS, beam_rate_hz=1.0, duration_s=60.0)
    result = run.result
    assert result.mission == "failure"
    assert result.failure == "timeout"
    # Each robot's beams are fresh for 0.3 s of every second, never all three at once.
    assert "held the fleet for stale data 100% of the time" in result.reason
    assert "(max 0.30 s)" in result.reason
    assert result.duration_s == 60.0


def test_a_corrupted_reading_stops_the_fleet_for_a_phantom_obstacle() -> None:
    def phantom(robot: str, beam_deg: int, t_s: float, range_m: float) -> float | None:
        return 0.5 if (robot, beam_deg) == ("robot2", 0) and 20.0 <= t_s < 20.5 else range_m

    result = run_offline(HALLWAY, SETTINGS, 20.0, 120.0, corrupt=phantom).result
    assert result.failure == "phantom_obstacle"
    assert result.robot == "robot2"
    assert result.duration_s == pytest.approx(20.0, abs=0.1)
    assert "its lidar_0 read 0.50 m but the true range was" in result.reason


def test_lost_front_readings_make_a_late_turn_that_corners_a_follower() -> None:
    def blind(robot: str, beam_deg: int, t_s: float, range_m: float) -> float | None:
        return None if (robot, beam_deg) == ("robot1", 0) and 8.0 <= t_s < 10.0 else range_m

    # With a lax staleness limit the leader drives on its last front reading (about 3.6 m,
    # up to 2 s old).
    lax = PlannerSettings.for_world(HALLWAY, max_age_s=3.0)
    result = run_offline(HALLWAY, lax, 20.0, 40.0, corrupt=blind).result
    assert result.failure == "timeout"
    assert "held the fleet for an obstacle" in result.reason
    assert "last: robot3 lidar_0 reads" in result.reason
    assert "corner 1: robot1 lidar_0 reads 2.05 m (turn point 3.00 m)" in result.reason


def test_a_real_obstacle_in_a_lane_holds_the_fleet_without_a_phantom() -> None:
    text = resources.files("arpz.mission").joinpath("maps/hallway.toml").read_text("utf-8")
    blocked = parse_map(
        text + "\n[[obstacles]]\ncentre_m = [5.0, 1.0]\nsize_m = [0.6, 0.6]\n",
        source="blocked",
        fmt="toml",
    )
    result = run_offline(blocked, PlannerSettings.for_world(blocked), 20.0, 30.0).result
    assert result.failure == "timeout"
    # robot3 (outer lane, y = 1) stops 1 m short of the box's face at x = 5.3.
    assert "last: robot3 lidar_0 reads 0.9" in result.reason
    assert "true range now 0.9" in result.reason
