"""The offline fault grids of docs/simulation.md (``python -m arpz.mission.grid``)."""

import itertools

import pytest

from arpz.mission.grid import intermittent, main, sweep, tally


def test_a_sweep_cuts_each_robot_off_once_per_run_from_each_half_second() -> None:
    cases = list(sweep("hallway", "downlink", ["robot1", "robot2"]))
    assert len(cases) == 2 * 2 * 118
    assert [o.start_s for o in cases[0].outages + cases[117].outages] == [1.0, 59.5]
    assert {case.label for case in cases} == {
        "robot1 downlink 3 s",
        "robot1 downlink 12 s",
        "robot2 downlink 3 s",
        "robot2 downlink 12 s",
    }


def test_intermittent_outages_are_drawn_from_the_seed() -> None:
    first, again = (list(intermittent("hallway_small", "link", ["robot1", "robot2"])) for _ in "ab")
    assert first == again and len(first) == 30
    gaps = [o for o in first[0].outages if o.robot == "robot1"]
    assert all(0.05 <= o.duration_s <= 0.8 for o in gaps)
    pauses = [b.start_s - (a.start_s + a.duration_s) for a, b in itertools.pairwise(gaps)]
    assert all(0.3 <= pause <= 4.0 for pause in pauses)


def test_a_tally_counts_verdicts_per_row() -> None:
    case = next(iter(sweep("hallway_small", "downlink", ["robot2"], durations_s=(3.0,))))
    assert tally([case]) == {("hallway_small", "robot2 downlink 3 s"): {"S": 1}}


@pytest.mark.parametrize(
    ("argument", "message"),
    [
        ("max_command_age=1", "not FIELD=VALUE with a PlannerSettings field"),
        ("max_command_age_s=soon", "could not convert"),
        ("max_command_age_s=0", "max_command_age_s must be > 0"),
    ],
)
def test_settings_given_on_the_command_line_are_checked(
    argument: str, message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit):
        main(["sweep", "--set", argument])
    assert message in capsys.readouterr().err
