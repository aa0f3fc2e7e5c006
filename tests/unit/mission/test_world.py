import json
import math
from pathlib import Path

import numpy as np
import pytest

from arpz.mission.kinematics import Pose
from arpz.mission.world import MapError, World, parse_map

SMALL_MAP = """
name = "box"
[mission]
leader = "a"
corridor_width_m = 2.0
[[walls]]
points = [[0, 0], [10, 0], [10, 4], [0, 4], [0, 0]]
[robots.a]
x_m = 5
y_m = 1
heading_deg = 90
"""


def test_builtin_hallway_is_a_4m_loop_round_a_block_with_three_homes() -> None:
    world = World.builtin("hallway")
    assert len(world.segments) == 8  # 4 outer walls + 4 sides of the central block
    assert world.robots == ("robot1", "robot2", "robot3")
    assert world.homes["robot1"] == pytest.approx(Pose(10.0, 2.0, math.pi))
    assert world.corridor_width_m == 4.0
    assert world.direction == "clockwise"
    assert world.loop_centre_m == (10.0, 6.0)
    # Every home is in its own lane, clear of the walls and of the other robots.
    for home in world.homes.values():
        assert world.clearance_m(home.x_m, home.y_m) == pytest.approx(1.0 if home.y_m != 2 else 2.0)


def test_clearance_is_distance_to_nearest_segment_including_its_ends() -> None:
    world = World.builtin()
    assert world.clearance_m(10.0, 2.0) == pytest.approx(2.0)
    # Off the end of the block's corner (4, 4): the nearest point is the corner itself.
    assert world.clearance_m(3.0, 3.0) == pytest.approx(math.sqrt(2.0))


def test_load_by_builtin_name_and_from_toml_and_json_files(tmp_path: Path) -> None:
    assert World.load("hallway").name == "hallway"
    toml_path = tmp_path / "box.toml"
    toml_path.write_text(SMALL_MAP)
    box = World.load(toml_path)
    assert box.robots == ("a",)
    assert box.loop_centre_m == (5.0, 2.0)  # no loop_centre given: middle of the walls
    json_path = tmp_path / "box.json"
    json_path.write_text(
        json.dumps(
            {
                "name": "box",
                "mission": {"leader": "a", "corridor_width_m": 2.0},
                "walls": [{"points": [[0, 0], [10, 0], [10, 4], [0, 4], [0, 0]]}],
                "robots": {"a": {"x_m": 5, "y_m": 1, "heading_deg": 90}},
                "obstacles": [{"centre_m": [8, 2], "size_m": [1, 2]}],
            }
        )
    )
    with_box = World.load(json_path)
    assert len(with_box.segments) == 4 + 4
    # The obstacle's left face is at x = 7.5: 2.5 m from a robot at (5, 2).
    assert with_box.clearance_m(5.0, 2.0) == pytest.approx(2.0)
    assert with_box.ray_ranges_m(5.0, 2.0, np.array([0.0]), 12.0)[0] == pytest.approx(2.5)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (("[[walls]]", "[[wals]]"), "unknown field `wals`"),
        (('leader = "a"', 'leader = "b"'), "mission.leader = 'b' has no home"),
        (("y_m = 1\n", "y_m = 0.1\n"), "closer than robot_radius_m"),
        (("[0, 4], [0, 0]]", "[0, 4], [0, 4]]"), "repeats a point"),
        (("[robots.a]", "[robots.A]"), "robots.A"),
        (("heading_deg = 90", 'heading_deg = "north"'), "Expected `float`, got `str`"),
    ],
)
def test_map_errors_name_the_file_and_the_field(change: tuple[str, str], message: str) -> None:
    text = SMALL_MAP.replace(*change)
    assert text != SMALL_MAP
    with pytest.raises(MapError, match=r"^box\.toml: ") as info:
        parse_map(text, source="box.toml", fmt="toml")
    assert message in str(info.value)


def test_load_refuses_unknown_suffix_and_missing_file(tmp_path: Path) -> None:
    with pytest.raises(MapError, match=r"must end in \.toml or \.json"):
        World.load(tmp_path / "map.yaml")
    with pytest.raises(MapError, match="cannot read"):
        World.load(tmp_path / "absent.toml")
    with pytest.raises(MapError, match="no built-in map 'maze'"):
        World.builtin("maze")
