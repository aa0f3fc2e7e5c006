import itertools
import math

import numpy as np
import pytest

from arpz.mission.judge import Judge, JudgeSettings
from arpz.mission.kinematics import Pose
from arpz.mission.vocabulary import EventKind, MissionEvent
from arpz.mission.world import World

HALLWAY = World.builtin()
LEADER_LOOP = [(10.0, 2.0), (2.0, 2.0), (2.0, 10.0), (18.0, 10.0), (18.0, 2.0), (10.0, 2.0)]
LOOP_LENGTH_M = 8 + 8 + 16 + 8 + 8


def lane(robot: str) -> list[tuple[float, float]]:
    """The leader's loop shifted by the robot's home offset: its lane."""
    home, lead = HALLWAY.homes[robot], HALLWAY.homes["robot1"]
    dx, dy = home.x_m - lead.x_m, home.y_m - lead.y_m
    return [(x + dx, y + dy) for x, y in LEADER_LOOP]


def walk(corners: list[tuple[float, float]], step_m: float = 0.1) -> list[Pose]:
    poses = []
    for (x0, y0), (x1, y1) in itertools.pairwise(corners):
        n = round(math.hypot(x1 - x0, y1 - y0) / step_m)
        heading = math.atan2(y1 - y0, x1 - x0)
        poses += [Pose(x0 + (x1 - x0) * i / n, y0 + (y1 - y0) * i / n, heading) for i in range(n)]
    return [*poses, Pose(*corners[-1], poses[-1].theta_rad)]


def event(
    t_s: float,
    kind: EventKind,
    robot: str = "robot1",
    *,
    beam_deg: int | None = None,
    range_m: float | None = None,
    corner: int | None = None,
) -> MissionEvent:
    return MissionEvent(
        t_s=t_s, kind=kind, robot=robot, text=f"{kind} text",
        beam_deg=beam_deg, range_m=range_m, corner=corner,
    )  # fmt: skip


def feed(judge: Judge, paths: dict[str, list[Pose]], *, dt_s: float = 0.1) -> None:
    for i in range(max(len(p) for p in paths.values())):
        for robot, path in paths.items():
            judge.on_pose(robot, i * dt_s, path[min(i, len(path) - 1)])


def test_success_when_every_robot_goes_round_its_lane_and_stops_at_home() -> None:
    judge = Judge(HALLWAY, JudgeSettings(time_limit_s=100.0))
    paths = {robot: walk(lane(robot)) for robot in HALLWAY.robots}
    feed(judge, paths)  # 1 m/s: the loop takes 48 s
    assert judge.result is None  # home, but the last step still moved 0.1 m in 0.1 s
    for robot, path in paths.items():
        judge.on_pose(robot, 48.1, path[-1])
    result = judge.result
    assert result is not None
    assert result.mission == "success"
    assert result.duration_s == pytest.approx(LOOP_LENGTH_M + 0.1)
    assert result.path_error_m == pytest.approx(0.0, abs=1e-9)
    assert result.progress == pytest.approx({"robot1": 1.0, "robot2": 1.0, "robot3": 1.0})


def test_home_without_going_round_is_not_success() -> None:
    judge = Judge(HALLWAY, JudgeSettings(time_limit_s=10.0))
    for t_s in (0.0, 1.0, 2.0):
        for robot, home in HALLWAY.homes.items():
            assert judge.on_pose(robot, t_s, home) is None
    result = judge.finish(2.0)
    assert result.mission == "failure"
    assert result.failure == "incomplete"
    assert "loop done: robot1 0%, robot2 0%, robot3 0%" in result.reason


def test_a_robot_round_the_loop_but_short_of_home_is_said_so() -> None:
    # robot2 stopped 0.8 m before its home: round the loop, but not home
    judge = Judge(HALLWAY, JudgeSettings(time_limit_s=60.0))
    paths = {robot: walk(lane(robot)) for robot in HALLWAY.robots}
    paths["robot2"] = paths["robot2"][:-8]
    feed(judge, paths)
    result = judge.finish(60.0)
    assert result.failure == "timeout"
    assert "robot1 100%, robot2 97% (0.80 m from home), robot3 100%" in result.reason


def test_path_error_is_the_followers_distance_from_the_shifted_leader_path() -> None:
    judge = Judge(HALLWAY)
    paths = {
        "robot1": walk([(10.0, 2.0), (5.0, 2.0)]),
        "robot2": walk([(11.0, 3.3), (6.0, 3.3)]),  # 0.3 m off its lane (home offset is 1, 1)
        "robot3": walk([(9.0, 1.0), (4.0, 1.0)]),  # exactly in its lane
    }
    feed(judge, paths)
    result = judge.finish(5.0)
    assert result.path_error_m == pytest.approx(0.15)  # half the points are 0.3 m off
    assert result.path_error_max_m == pytest.approx(0.3)


def test_collision_with_a_wall_names_the_robot_the_place_and_the_last_turn() -> None:
    judge = Judge(HALLWAY)
    judge.on_event(event(9.0, "turn_started", corner=1))
    for robot, home in HALLWAY.homes.items():
        judge.on_pose(robot, 10.0, home)
    assert judge.result is None
    result = judge.on_pose("robot3", 10.5, Pose(9.0, 0.19, math.pi))  # radius 0.2 from y = 0
    assert result is not None
    assert result.failure == "collision"
    assert result.robot == "robot3"
    assert result.where_m == pytest.approx((9.0, 0.19))
    assert result.reason.startswith("collision: robot3 touched a wall at (9.00, 0.19) at t=10.5 s")
    assert "last turn started at t=9.0 s: turn_started text" in result.reason
    # The verdict is final: later poses do not change it.
    assert judge.on_pose("robot3", 11.0, HALLWAY.homes["robot3"]) is result


def test_robots_closer_than_two_radii_collide() -> None:
    judge = Judge(HALLWAY)
    judge.on_pose("robot1", 0.0, Pose(10.0, 2.0, math.pi))
    assert judge.on_pose("robot2", 0.0, Pose(10.5, 2.0, math.pi)) is None  # 0.5 m > 0.4 m
    result = judge.on_pose("robot2", 0.1, Pose(10.35, 2.0, math.pi))
    assert result is not None and result.failure == "collision"
    assert "robot2 and robot1 collided" in result.reason


def test_timeout_says_how_far_they_got_and_how_long_stale_data_held_them() -> None:
    judge = Judge(HALLWAY, JudgeSettings(time_limit_s=40.0))
    for robot, home in HALLWAY.homes.items():
        judge.on_pose(robot, 0.0, home)
    judge.on_event(event(0.0, "stale_stop", "robot2", beam_deg=0))
    judge.on_event(event(5.0, "stale_stop", "robot3", beam_deg=0))  # same hold, new culprit
    judge.on_event(event(30.0, "resumed"))
    assert judge.check(39.9) is None
    result = judge.check(40.0)
    assert result is not None
    assert result.failure == "timeout"
    assert result.duration_s == 40.0
    assert result.reason == (
        "timeout: not all robots home within 40 s (loop done: robot1 0%, robot2 0%, robot3 0%); "
        "the planner held the fleet for stale data 75% of the time (1 stop; last: stale_stop text)"
    )


def test_stop_for_an_obstacle_that_is_not_there_is_a_phantom() -> None:
    judge = Judge(HALLWAY)
    judge.on_pose("robot2", 20.0, HALLWAY.homes["robot2"])  # facing 11 m of empty corridor
    result = judge.on_event(event(20.0, "obstacle_stop", "robot2", beam_deg=0, range_m=0.5))
    assert result is not None
    assert result.failure == "phantom_obstacle"
    assert result.robot == "robot2"
    assert "its lidar_0 read 0.50 m but the true range was 11.00 m" in result.reason


def test_stop_for_a_real_wall_ahead_is_not_a_phantom() -> None:
    judge = Judge(HALLWAY, JudgeSettings(time_limit_s=60.0))
    judge.on_pose("robot3", 20.0, Pose(9.0, 1.0, -math.pi / 2))  # facing the outer wall, 1 m
    assert judge.on_event(event(20.0, "obstacle_stop", "robot3", beam_deg=0, range_m=0.98)) is None
    result = judge.check(60.0)
    assert result is not None and result.failure == "timeout"
    assert "held the fleet for an obstacle 67% of the time" in result.reason
    assert "true range now 1.00 m" in result.reason


def test_paths_keep_every_pose_judged() -> None:
    judge = Judge(HALLWAY)
    judge.on_pose("robot1", 0.0, Pose(10.0, 2.0, math.pi))
    judge.on_pose("robot1", 0.5, Pose(9.5, 2.0, math.pi))
    paths = judge.paths()
    assert np.array_equal(paths["robot1"], [[0.0, 10.0, 2.0, math.pi], [0.5, 9.5, 2.0, math.pi]])
    assert paths["robot2"].shape == (0, 4)
