"""The closed loop without a network: the hallway mission end to end on simulated time."""

from importlib import resources
from typing import Literal

import numpy as np
import pytest

from arpz.mission.hallway import PlannerSettings
from arpz.mission.offline import Outage, run_offline
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


@pytest.mark.parametrize(
    ("kind", "duration_s"), [("link", 3.0), ("link", 12.0), ("frozen", 3.0), ("frozen", 12.0)]
)
def test_the_leader_cut_off_in_a_corner_leaves_no_follower_driving_into_a_wall(
    kind: Literal["link", "frozen"], duration_s: float
) -> None:
    # Issue 39: robot1's link dead (it drives on its last command until its 0.5 s timeout) or
    # its process frozen (it does not move), in the first corner. The planner holds the fleet
    # 0.3 s after robot1's last reading, so robot1 turned more (link) or less (frozen) than the
    # followers; steered with robot1's velocity alone, robot3 (link) or robot2 (frozen) kept
    # that error and drove into a wall on the next leg. Now each is steered back into its lane.
    outage = Outage("robot1", 9.5, duration_s, kind)
    run = run_offline(HALLWAY, SETTINGS, 20.0, 150.0, noise_std_m=0.01, outages=[outage])
    assert run.result.mission == "success", run.result.reason
    assert run.result.duration_s == pytest.approx(LOOP_M / 0.8 + duration_s, abs=1.5)
    stale = [e for e in run.events if e.kind == "stale_stop" and e.t_s > 1.0]
    # robot1's readings first; when they are back, its commands until it acknowledges them
    assert {e.robot for e in stale} == {"robot1"}
    assert stale[0].beam_deg is not None
    assert stale[0].t_s == pytest.approx(9.5 + SETTINGS.max_age_s, abs=0.1)
    steered = {e.robot for e in run.events if e.kind == "off_lane"}
    assert steered and steered <= {"robot2", "robot3"}
    assert run.result.path_error_max_m is not None and run.result.path_error_max_m < 0.5


def test_an_outage_names_a_robot_of_the_fleet_and_a_positive_duration() -> None:
    with pytest.raises(ValueError, match="duration_s > 0"):
        Outage("robot1", 1.0, 0.0)
    with pytest.raises(ValueError, match="'robot9', which is not in the fleet"):
        run_offline(HALLWAY, SETTINGS, 20.0, 1.0, outages=[Outage("robot9", 0.5, 1.0)])


@pytest.mark.parametrize("kind", ["uplink", "downlink"])
def test_a_one_way_outage_loses_one_direction(kind: Literal["uplink", "downlink"]) -> None:
    # 2 s into the first leg. Uplink: robot1's readings stop, the planner holds the whole fleet,
    # every robot gets the STOP. Downlink: robot1 hears nothing and its body stops at its 0.5 s
    # timeout while its readings keep coming; its commands go unacknowledged, and the planner
    # holds the fleet for that (issue 39: before, it moved the others on, 1.8 m here).
    run = run_offline(
        HALLWAY, SETTINGS, 20.0, 6.0, outages=[Outage("robot1", 2.0, 3.0, kind)], noise_std_m=0.01
    )
    stale = [e for e in run.events if e.kind == "stale_stop" and e.t_s > 1.0]
    robot1, robot2 = run.paths["robot1"], run.paths["robot2"]
    at = {t: int(np.searchsorted(robot1[:, 0], t)) for t in (2.6, 4.9)}

    def moved(path: np.ndarray) -> float:
        return float(np.hypot(*(path[at[4.9], 1:3] - path[at[2.6], 1:3])))

    assert {e.robot for e in stale} == {"robot1"}  # uplink: its acknowledgements lost too
    assert moved(robot1) == moved(robot2) == 0.0
    if kind == "uplink":
        assert stale[0].beam_deg is not None
        assert stale[0].t_s == pytest.approx(2.0 + SETTINGS.max_age_s, abs=0.06)
    else:
        assert stale[0].text.startswith("robot1 commands: unacknowledged for 0.4")
        # the last acknowledgement before the cut came up to a heartbeat period before it
        assert 2.0 + SETTINGS.max_command_age_s - 0.1 <= stale[0].t_s <= 2.45


@pytest.mark.parametrize("followers_home", [True, False])
def test_followers_left_behind_drive_on_to_their_own_home_marks(followers_home: bool) -> None:
    # robot1's link dead 0.45 s six times on the last leg: each time it drove on its last
    # command to its watchdog while the others were held for its stale readings, and ended
    # 0.6 m ahead of them. The planner cannot see that (the beams do not see robots), but each
    # follower's own front beam says where its home is.
    settings = SETTINGS if followers_home else PlannerSettings.for_world(HALLWAY, home_fronts_m={})
    outages = [Outage("robot1", 53.0 + 1.5 * i, 0.45, "link") for i in range(6)]
    run = run_offline(HALLWAY, settings, 20.0, 150.0, noise_std_m=0.01, outages=outages)
    homes = [e for e in run.events if e.kind == "home"]
    if followers_home:
        assert run.result.mission == "success", run.result.reason
        assert [e.robot for e in homes] == ["robot1", "robot2", "robot3"]
        assert "robot2 lidar_0 reads 11.00 m (home mark 11.00 m), 0.6" in homes[1].text
    else:
        assert run.result.failure == "timeout"
        assert "robot2 97% (0.62 m from home)" in run.result.reason
