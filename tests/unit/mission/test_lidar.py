import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from arpz.mission.kinematics import Pose
from arpz.mission.lidar import BEAM_ANGLES_DEG, Lidar, beam_endpoints, beam_of_topic, beam_topic
from arpz.mission.world import World

HALLWAY = World.builtin()
ROOT2 = math.sqrt(2.0)


def test_leader_home_scan_matches_hand_geometry() -> None:
    # robot1 at (10, 2) heading west, 2 m from the outer wall (south) and from the block (north).
    ranges = Lidar(HALLWAY).scan(Pose(10.0, 2.0, math.pi))
    expected = {
        0: 10.0,  # west to x = 0, perpendicular
        45: 2 * ROOT2,  # south-west to y = 0 at 45 degrees
        90: 2.0,  # left is south
        135: 2 * ROOT2,
        180: 10.0,  # east to x = 20
        225: 2 * ROOT2,  # north-east onto the block's bottom face (y = 4 at x = 12)
        270: 2.0,  # right is north: the block
        315: 2 * ROOT2,
    }
    assert ranges == pytest.approx([expected[deg] for deg in BEAM_ANGLES_DEG])


def test_ray_aimed_exactly_at_a_corner_hits_it() -> None:
    lidar = Lidar(HALLWAY, beams_deg=(0,))
    assert lidar.scan(Pose(2.0, 2.0, math.radians(225)))[0] == pytest.approx(2 * ROOT2)
    # The block's outer corner (16, 8) seen from (18, 10).
    assert lidar.scan(Pose(18.0, 10.0, math.radians(225)))[0] == pytest.approx(2 * ROOT2)


def test_nothing_within_max_range_reads_max_range() -> None:
    assert Lidar(HALLWAY, max_range_m=5.0).scan(Pose(10.0, 2.0, math.pi))[0] == 5.0
    # Top corridor looking east: the far wall is 18 m away, beyond the A2M8's 12 m.
    assert Lidar(HALLWAY).scan(Pose(2.0, 10.0, 0.0))[0] == 12.0


def test_noise_is_seeded_and_spares_max_range_readings() -> None:
    pose = Pose(2.0, 10.0, 0.0)
    first = Lidar(HALLWAY, noise_std_m=0.05, seed=7).scan(pose)
    again = Lidar(HALLWAY, noise_std_m=0.05, seed=7).scan(pose)
    assert np.array_equal(first, again)
    true = Lidar(HALLWAY).scan(pose)
    assert first[0] == 12.0  # a "no return" stays exact
    assert not np.array_equal(first[1:], true[1:])
    assert np.all(np.abs(first - true) < 0.3)  # 6 sigma


def test_noise_has_the_requested_spread() -> None:
    lidar = Lidar(HALLWAY, noise_std_m=0.05, seed=1)
    errors = np.array([lidar.scan(Pose(10.0, 2.0, math.pi))[2] - 2.0 for _ in range(2000)])
    assert abs(errors.mean()) < 0.005
    assert errors.std() == pytest.approx(0.05, rel=0.1)


def test_beam_endpoints_are_where_the_rays_hit() -> None:
    pose = Pose(10.0, 2.0, math.pi)
    ends = beam_endpoints(pose, Lidar(HALLWAY).scan(pose))
    assert ends[0] == pytest.approx([0.0, 2.0])  # front: the west wall
    assert ends[2] == pytest.approx([10.0, 0.0])  # left: the outer wall, south
    assert ends[5] == pytest.approx([12.0, 4.0])  # 225: the block's face, north-east


def test_topic_names_round_trip() -> None:
    assert [beam_topic(d) for d in (0, 45, 315)] == ["lidar_0", "lidar_45", "lidar_315"]
    assert all(beam_of_topic(beam_topic(d)) == d for d in BEAM_ANGLES_DEG)
    assert beam_of_topic("lidar_30") is None
    assert beam_of_topic("lidar_x") is None
    assert beam_of_topic("imu") is None
    with pytest.raises(ValueError, match="no beam at 30"):
        beam_topic(30)


# Points in the corridor (outside the block, inside the outer wall, off the walls).
corridor_points = st.tuples(st.floats(0.3, 19.7), st.floats(0.3, 11.7)).filter(
    lambda p: not (3.7 < p[0] < 16.3 and 3.7 < p[1] < 8.3)
)


@given(corridor_points, st.floats(-math.pi, math.pi))
def test_every_beam_ends_on_a_wall_no_closer_than_the_nearest_wall(
    point: tuple[float, float], theta_rad: float
) -> None:
    x_m, y_m = point
    pose = Pose(x_m, y_m, theta_rad)
    ranges = Lidar(HALLWAY, max_range_m=30.0).scan(pose)
    assert np.all(ranges >= HALLWAY.clearance_m(x_m, y_m) - 1e-9)
    for deg, range_m in zip(BEAM_ANGLES_DEG, ranges, strict=True):
        angle = theta_rad + math.radians(deg)
        end_x, end_y = x_m + range_m * math.cos(angle), y_m + range_m * math.sin(angle)
        assert HALLWAY.clearance_m(end_x, end_y) == pytest.approx(0.0, abs=1e-6)
