import math

import msgspec
import pytest
from hypothesis import given
from hypothesis import strategies as st

from arpz.mission.hallway import HallwayPlanner, PlannerSettings
from arpz.mission.kinematics import Pose
from arpz.mission.lidar import BEAM_ANGLES_DEG, Lidar
from arpz.mission.vocabulary import STOP, VelocityCommand
from arpz.mission.world import World

HALLWAY = World.builtin()
LIDAR = Lidar(HALLWAY)
SETTINGS = PlannerSettings.for_world(HALLWAY)
HOMES = HALLWAY.homes
QUARTER_TURN_S = (math.pi / 2) / (SETTINGS.cruise_speed_m_s / SETTINGS.turn_radius_m)


def see(planner: HallwayPlanner, robot: str, pose: Pose, t_s: float, **override: float) -> None:
    """Give the planner one scan of ``robot`` at ``pose`` (beams by angle can be overridden)."""
    for deg, range_m in zip(BEAM_ANGLES_DEG, LIDAR.scan(pose), strict=True):
        planner.on_range(robot, deg, override.get(f"b{deg}", float(range_m)), t_s)


def see_fleet(planner: HallwayPlanner, leader: Pose, t_s: float, **override: float) -> None:
    see(planner, "robot1", leader, t_s, **override)
    see(planner, "robot2", HOMES["robot2"], t_s)
    see(planner, "robot3", HOMES["robot3"], t_s)


def kinds(planner: HallwayPlanner) -> list[str]:
    return [e.kind for e in planner.pop_events()]


def test_settings_for_the_hallway_come_from_the_map() -> None:
    assert SETTINGS.leader == "robot1"
    assert SETTINGS.followers == ("robot2", "robot3")
    assert SETTINGS.turn == "right"
    assert SETTINGS.home_front_m == pytest.approx(10.0)  # robot1's home is 10 m from the west wall
    assert SETTINGS.home_fronts_m == pytest.approx({"robot2": 11.0, "robot3": 9.0})
    assert SETTINGS.turn_point_m == pytest.approx(3.0)  # half the 4 m corridor + 1 m turn radius


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"max_age_s": 0.0}, "max_age_s must be > 0"),
        ({"max_command_age_s": 0.0}, "max_command_age_s must be > 0"),
        ({"home_fronts_m": {"robot9": 3.0}}, "home_fronts_m names 'robot9', not a follower"),
        ({"obstacle_range_m": 3.5}, "below the turn point 3.00 m"),
        ({"home_front_m": 15.0}, "the leader cannot see its home mark"),
        ({"followers": ["robot1"]}, "leader 'robot1' is also a follower"),
        ({"obstacle_beams_deg": [30]}, "obstacle beam 30"),
    ],
)
def test_settings_refuse_what_cannot_work(fields: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        msgspec.convert(fields, type=PlannerSettings)


def test_unknown_settings_field_is_an_error() -> None:
    with pytest.raises(msgspec.ValidationError, match="max_age"):
        msgspec.convert({"max_age": 1.0}, type=PlannerSettings)


def test_without_data_the_fleet_is_held_and_says_why() -> None:
    planner = HallwayPlanner(SETTINGS)
    assert planner.tick(0.0) == {"robot1": STOP, "robot2": STOP, "robot3": STOP}
    (event,) = planner.pop_events()
    assert event.kind == "stale_stop"
    assert "no reading yet" in event.text


def test_fresh_clear_data_moves_every_robot_with_the_leaders_velocity() -> None:
    planner = HallwayPlanner(SETTINGS)
    see_fleet(planner, HOMES["robot1"], 0.0)
    commands = planner.tick(0.05)
    # Centred and parallel at home: straight ahead at cruise speed, the same for all three.
    assert len(set(commands.values())) == 1
    assert commands["robot2"].v_m_s == 0.8
    assert commands["robot2"].omega_rad_s == pytest.approx(0.0, abs=1e-12)
    assert kinds(planner) == ["started"]
    assert planner.phase == "following"


def test_data_older_than_max_age_stops_the_fleet_until_fresh_again() -> None:
    planner = HallwayPlanner(SETTINGS)
    see_fleet(planner, HOMES["robot1"], 0.0)
    planner.tick(0.3)  # exactly max_age_s old: still usable
    assert kinds(planner) == ["started"]
    see(planner, "robot1", HOMES["robot1"], 0.2)
    see(planner, "robot2", HOMES["robot2"], 0.2)
    assert set(planner.tick(0.45).values()) == {STOP}  # robot3's beams are 0.45 s old
    (event,) = planner.pop_events()
    assert (event.kind, event.robot, event.beam_deg) == ("stale_stop", "robot3", 0)
    assert event.age_s == pytest.approx(0.45)
    assert planner.hold == "stale"
    see_fleet(planner, HOMES["robot1"], 0.5)
    assert planner.tick(0.5)["robot3"].v_m_s == 0.8
    assert kinds(planner) == ["resumed"]


def test_commands_a_robot_leaves_unacknowledged_hold_the_fleet_like_stale_data() -> None:
    # Issue 39: robot2's commands are lost (a downlink-only failure) while its readings still
    # arrive: it drives on its last command to its watchdog, so the fleet must not go on
    planner = HallwayPlanner(SETTINGS)
    see_fleet(planner, HOMES["robot1"], 0.0)
    planner.on_command_ack("robot2", 0.05)  # its oldest unacknowledged command: sent at 0.05 s
    assert planner.tick(0.05)["robot2"].v_m_s == 0.8
    assert kinds(planner) == ["started"]
    see_fleet(planner, HOMES["robot1"], 0.4)
    assert planner.tick(0.45)["robot1"].v_m_s == 0.8  # exactly max_command_age_s: still fine
    see_fleet(planner, HOMES["robot1"], 0.5)
    assert set(planner.tick(0.5).values()) == {STOP}
    (event,) = planner.pop_events()
    assert (event.kind, event.robot, event.beam_deg) == ("stale_stop", "robot2", None)
    assert event.text == "robot2 commands: unacknowledged for 0.45 s (max 0.40 s): fleet held"
    assert event.age_s == pytest.approx(0.45)
    assert planner.hold == "stale"
    # stale readings come first: a robot cut off both ways is named by its readings
    see(planner, "robot1", HOMES["robot1"], 0.6)
    see(planner, "robot2", HOMES["robot2"], 0.6)
    planner.tick(1.6)
    (event,) = planner.pop_events()
    assert (event.robot, event.beam_deg) == ("robot3", 0)
    see_fleet(planner, HOMES["robot1"], 1.7)
    planner.on_command_ack("robot2", None)  # every command acknowledged
    assert planner.tick(1.7)["robot2"].v_m_s == 0.8
    (event,) = planner.pop_events()
    assert event.kind == "resumed" and event.text.startswith("data fresh again")
    planner.on_command_ack("robot2", 1.0)
    planner.on_command_ack("robot9", 0.0)  # not in the fleet: ignored
    see_fleet(planner, HOMES["robot1"], 1.75)
    assert set(planner.tick(1.75).values()) == {STOP}
    planner.on_command_ack("robot2", None)
    assert planner.tick(1.8)["robot2"].v_m_s == 0.8
    assert [e.text.split(" after")[0] for e in planner.pop_events()] == [
        "robot2 commands: unacknowledged for 0.75 s (max 0.40 s): fleet held",
        "commands acknowledged again",
    ]


def test_commands_are_not_watched_with_an_infinite_limit() -> None:
    planner = HallwayPlanner(PlannerSettings.for_world(HALLWAY, max_command_age_s=math.inf))
    see_fleet(planner, HOMES["robot1"], 0.0)
    planner.on_command_ack("robot1", -100.0)
    assert planner.tick(0.05)["robot1"].v_m_s == 0.8


def test_an_obstacle_ahead_of_a_follower_stops_all_until_it_reads_clear_with_margin() -> None:
    planner = HallwayPlanner(SETTINGS)
    see_fleet(planner, HOMES["robot1"], 0.0)
    planner.tick(0.0)
    planner.pop_events()
    planner.on_range("robot2", 0, 0.9, 0.1)
    assert set(planner.tick(0.1).values()) == {STOP}
    (event,) = planner.pop_events()
    assert (event.kind, event.robot, event.range_m) == ("obstacle_stop", "robot2", 0.9)
    see_fleet(
        planner,
        HOMES["robot1"],
        0.2,
    )
    planner.on_range("robot2", 0, 1.1, 0.2)  # beyond 1.0 but inside the 0.2 m clear margin
    assert set(planner.tick(0.2).values()) == {STOP}
    assert kinds(planner) == []
    planner.on_range("robot2", 0, 1.25, 0.3)
    planner.on_range("robot3", 0, 8.0, 0.3)
    see(planner, "robot1", HOMES["robot1"], 0.3)
    assert planner.tick(0.3)["robot1"].v_m_s == 0.8
    assert kinds(planner) == ["clear"]


def test_leader_left_of_the_centreline_steers_right() -> None:
    planner = HallwayPlanner(SETTINGS)
    # Heading west, the left wall is the outer wall (south): 0.5 m left of the middle.
    see_fleet(planner, Pose(10.0, 1.5, math.pi), 0.0)
    # Wanted heading -0.6 rad/m * 0.5 m = -0.3 rad; omega = 1.5/s * (-0.3 - 0) = -0.45 rad/s.
    assert planner.tick(0.0)["robot1"].omega_rad_s == pytest.approx(-0.45)


def test_leader_turned_towards_a_wall_turns_back() -> None:
    planner = HallwayPlanner(SETTINGS)
    see_fleet(planner, Pose(10.0, 2.0, math.pi + 0.1), 0.0)  # 0.1 rad towards the left wall
    assert planner.tick(0.0)["robot1"].omega_rad_s == pytest.approx(-1.5 * 0.1)


def test_one_side_open_centres_on_the_other_wall() -> None:
    planner = HallwayPlanner(SETTINGS)
    # At x = 5 heading west the right-hand beams look past the block's corner into the west
    # corridor: only the outer wall (left) is usable, 0.3 m nearer than half the width.
    see_fleet(planner, Pose(5.0, 1.7, math.pi), 0.0)
    assert planner.tick(0.0)["robot1"].omega_rad_s == pytest.approx(1.5 * -0.6 * 0.3)


def test_corner_turn_lasts_a_quarter_circle_and_does_not_retrigger_on_old_readings() -> None:
    planner = HallwayPlanner(SETTINGS)
    near_corner = Pose(2.95, 2.0, math.pi)  # front reads 2.95 m, inside the 3 m turn point
    see_fleet(planner, near_corner, 0.0)
    assert set(planner.tick(0.0).values()) == {VelocityCommand(0.8, -0.8)}  # right, radius 1 m
    assert kinds(planner) == ["started", "turn_started"]
    t_s = 0.0
    while planner.phase == "turning":
        t_s = round(t_s + 0.05, 10)
        see_fleet(planner, near_corner, t_s)  # the planner trusts its commands, not these ranges
        planner.tick(t_s)
    # The turn ends at the first tick after pi/2 rad at 0.8 rad/s (1.963 s).
    assert t_s == pytest.approx(math.ceil(QUARTER_TURN_S / 0.05) * 0.05)
    assert kinds(planner)[-1] == "turn_done"
    assert planner.corners_done == 1
    # Readings still at 2.95 m (taken after the turn) do not start corner 2 ...
    see_fleet(planner, near_corner, t_s + 0.05)
    assert planner.tick(t_s + 0.05)["robot1"].omega_rad_s != -0.8
    assert planner.phase == "following"
    # ... until the front has read clear of the corner (> 3 + 1 m) once.
    see_fleet(planner, Pose(2.0, 5.0, math.pi / 2), t_s + 0.1)
    planner.tick(t_s + 0.1)
    see_fleet(planner, Pose(2.0, 9.05, math.pi / 2), t_s + 0.15)
    planner.tick(t_s + 0.15)
    assert planner.phase == "turning"
    assert [e.corner for e in planner.pop_events() if e.kind == "turn_started"] == [2]


def test_home_after_the_last_corner_when_front_reaches_the_mark_parallel_to_the_walls() -> None:
    # A one-corner mission: home is up the west corridor, 5 m short of its north wall.
    planner = HallwayPlanner(msgspec.structs.replace(SETTINGS, corners=1, home_front_m=5.0))
    see_fleet(planner, Pose(2.95, 2.0, math.pi), 0.0)
    planner.tick(0.0)
    see_fleet(planner, Pose(2.0, 3.95, math.pi / 2), QUARTER_TURN_S)  # front 8.05 m: re-armed
    planner.tick(QUARTER_TURN_S)  # the whole quarter turn in one tick interval
    assert planner.corners_done == 1
    assert planner.phase == "following"
    # Front 4.9 m but slanted 0.2 rad towards the west wall: not taken as home.
    see_fleet(planner, Pose(2.0, 7.2, math.pi / 2 + 0.2), 2.1)
    assert LIDAR.scan(Pose(2.0, 7.2, math.pi / 2 + 0.2))[0] < 5.0
    assert planner.tick(2.1)["robot1"].v_m_s == 0.8
    see_fleet(planner, Pose(2.0, 7.05, math.pi / 2), 2.2)
    assert set(planner.tick(2.2).values()) == {STOP}
    assert kinds(planner)[-1] == "home"
    assert planner.phase == "home"
    assert set(planner.tick(5.0).values()) == {STOP}


def test_home_right_after_the_last_corner_waits_for_the_leader_to_settle() -> None:
    # The home mark (8.5 m) is beyond what the front reads at the turn's end (8.05 m): a
    # reading there counts only once the leader has seen beyond the mark or had home_settle_s
    # to straighten up (in the lab a leader 16 degrees over-turned read 5.28 m at a corner's
    # exit, its side beams passed it as parallel, and the fleet stopped 3.8 m from home)
    planner = HallwayPlanner(msgspec.structs.replace(SETTINGS, corners=1, home_front_m=8.5))
    see_fleet(planner, Pose(2.95, 2.0, math.pi), 0.0)
    planner.tick(0.0)
    see_fleet(planner, Pose(2.0, 3.95, math.pi / 2), QUARTER_TURN_S)
    planner.tick(QUARTER_TURN_S)
    assert planner.corners_done == 1
    for t_s in (QUARTER_TURN_S + 0.05, QUARTER_TURN_S + 0.5):
        see_fleet(planner, Pose(2.0, 3.95, math.pi / 2), t_s)
        assert planner.tick(t_s)["robot1"].v_m_s == 0.8
    settled_s = QUARTER_TURN_S + SETTINGS.home_settle_s
    see_fleet(planner, Pose(2.0, 4.0, math.pi / 2), settled_s)
    assert set(planner.tick(settled_s).values()) == {STOP}
    assert planner.phase == "home"


def test_a_stale_leader_holds_the_fleet_and_a_follower_it_left_turned_is_steered_back() -> None:
    # Issue 39: robot1's link died in a corner. The planner held the fleet for its stale data,
    # but robot1, cut off, drove on its last command until its watchdog stopped it, 0.2 s after
    # robot2 had been stopped: when the data came back robot2 was turned 9 degrees from robot1.
    # Steered with robot1's velocity alone, it kept that error and drove into the wall 10 m on.
    planner = HallwayPlanner(SETTINGS)
    see_fleet(planner, HOMES["robot1"], 0.0)
    planner.tick(0.0)
    assert kinds(planner) == ["started"]
    for t_s in (0.1, 0.2, 0.3, 0.4):  # robot1 silent: its followers' beams keep coming
        see(planner, "robot2", HOMES["robot2"], t_s)
        see(planner, "robot3", HOMES["robot3"], t_s)
        commands = planner.tick(t_s)
    assert set(commands.values()) == {STOP}  # the whole fleet, not only the silent leader
    (event,) = planner.pop_events()
    assert (event.kind, event.robot) == ("stale_stop", "robot1")
    assert event.age_s == pytest.approx(0.4)
    turned = Pose(HOMES["robot2"].x_m, HOMES["robot2"].y_m, HOMES["robot2"].theta_rad + 0.16)
    for t_s in (3.0, 3.05, 3.1):  # fresh again; robot2 is seen turned on three scans in a row
        see(planner, "robot1", HOMES["robot1"], t_s)
        see(planner, "robot2", turned, t_s)
        see(planner, "robot3", HOMES["robot3"], t_s)
        commands = planner.tick(t_s)
    assert commands["robot1"] == commands["robot3"]
    assert commands["robot1"].v_m_s == 0.8
    assert commands["robot1"].omega_rad_s == pytest.approx(0.0, abs=1e-9)
    # robot2 (in its lane, 0.16 rad to the left of robot1's heading) turns back right
    assert commands["robot2"].v_m_s == 0.8
    assert commands["robot2"].omega_rad_s == pytest.approx(1.5 * -0.16, abs=1e-6)
    events = planner.pop_events()
    assert [e.kind for e in events] == ["resumed", "off_lane"]
    assert events[1].robot == "robot2"
    assert events[1].text == "robot2 is in its lane, turned +9.2 deg from robot1: steered back"
    # ... until it is parallel again: then every robot has the leader's velocity once more
    see_fleet(planner, HOMES["robot1"], 3.15)
    commands = planner.tick(3.15)
    assert len(set(commands.values())) == 1
    assert kinds(planner) == ["in_lane"]


# The leader mid-leg on each of the four legs (clockwise from home), where both robots see walls.
LEGS = [
    Pose(10.0, 2.0, math.pi),
    Pose(2.0, 5.5, math.pi / 2),
    Pose(10.0, 10.0, 0.0),
    Pose(18.0, 6.5, -math.pi / 2),
]


@pytest.mark.parametrize("leg", range(4))
def test_a_followers_lane_turns_with_the_fleet_at_each_corner(leg: int) -> None:
    # Each follower's path is the leader's shifted by its home offset, so on each leg its lane is
    # on another side of the leader: robot2 (+1, +1) m is right of it, right, left, left.
    planner = HallwayPlanner(SETTINGS)
    planner._corners_done = leg
    leader = LEGS[leg]
    see(planner, "robot1", leader, 0.0)
    for robot, shift_m in (("robot2", 1.0), ("robot3", -1.0)):
        in_lane = Pose(leader.x_m + shift_m, leader.y_m + shift_m, leader.theta_rad)
        see(planner, robot, in_lane, 0.0)
        assert planner.lane_error(robot, 0.0) == pytest.approx((0.0, 0.0), abs=1e-6)
        # 0.3 m to its left (the leader's left: the heading turned a quarter left)
        left = leader.theta_rad + math.pi / 2
        aside = Pose(in_lane.x_m + 0.3 * math.cos(left), in_lane.y_m + 0.3 * math.sin(left), 0.0)
        see(planner, robot, aside._replace(theta_rad=leader.theta_rad), 0.1)
        see(planner, "robot1", leader, 0.1)
        assert planner.lane_error(robot, 0.1) == pytest.approx((0.3, 0.0), abs=1e-6)
    assert SETTINGS.lanes_m == {
        "robot2": pytest.approx((-1.0, -1.0)),
        "robot3": pytest.approx((1.0, 1.0)),
    }


def test_inputs_the_planner_ignores() -> None:
    planner = HallwayPlanner(SETTINGS)
    assert planner.on_range("robot1", 0, 5.0, 1.0)
    assert not planner.on_range("robot1", 0, 4.0, 0.5)  # older than what it holds
    assert not planner.on_range("robot7", 0, 4.0, 2.0)
    assert not planner.on_range("robot1", 0, float("nan"), 2.0)
    assert planner.on_topic("robot1", "lidar_45", 3.0, 2.0)
    assert not planner.on_topic("robot1", "imu", 3.0, 2.0)
    with pytest.raises(ValueError, match="no beam at 10"):
        planner.on_range("robot1", 10, 1.0, 2.0)


readings = st.lists(
    st.tuples(
        st.sampled_from(["robot1", "robot2", "robot3"]),
        st.just(0) | st.sampled_from(BEAM_ANGLES_DEG),  # front beams often: they stop the fleet
        st.floats(0.0, 12.0) | st.floats(0.8, 1.3),  # ranges near the obstacle range often
        st.floats(0.0, 0.5),  # how long before the tick the reading was taken
    ),
    max_size=10,
)
# Each round: maybe a whole fleet scan from the homes (taken 0 to 0.5 s before the tick), then
# odd readings on top; so the planner sees fresh, stale, clear and blocked fleets in turn.
rounds = st.lists(st.tuples(st.none() | st.floats(0.0, 0.5), readings), min_size=1, max_size=8)


@given(rounds)
def test_the_fleet_never_moves_on_stale_data_or_with_an_obstacle_ahead(
    plan: list[tuple[float | None, list[tuple[str, int, float, float]]]],
) -> None:
    planner = HallwayPlanner(SETTINGS)
    now_s = 0.0
    for scan_age_s, batch in plan:
        now_s += 0.1
        if scan_age_s is not None:
            see_fleet(planner, HOMES["robot1"], now_s - scan_age_s)
        for robot, deg, range_m, age_s in batch:
            planner.on_range(robot, deg, range_m, now_s - age_s)
        commands = planner.tick(now_s)
        # one speed for the whole fleet (a follower out of its lane may turn differently)
        assert len({c.v_m_s for c in commands.values()}) == 1
        if commands["robot1"] == STOP:
            assert set(commands.values()) == {STOP}
            continue
        held = planner._latest  # what the planner holds, checked against the documented rules
        needed = [("robot1", d) for d in (0, 45, 90, 135, 225, 270, 315)]
        needed += [(robot, d) for robot in ("robot2", "robot3") for d in (0, 45, 315)]
        assert all(now_s - held[key][1] <= SETTINGS.max_age_s + 1e-9 for key in needed)
        assert held[("robot2", 0)][0] >= SETTINGS.obstacle_range_m
        assert held[("robot3", 0)][0] >= SETTINGS.obstacle_range_m
        assert all(held[key][0] >= SETTINGS.clearance_m for key in needed if key[1] in (0, 45, 315))
