"""The lab's profiles: names parsed, numbers as documented, schedules drawn as specified."""

from __future__ import annotations

import itertools
import random

import pytest

from arpz.lab.profiles import (
    CLEAN,
    LEAD_S,
    MIN_DWELL_S,
    PROFILES,
    GilbertElliott,
    LinkState,
    bursty,
    dead_zone,
    parse_assignments,
    parse_profile,
    schedule,
)


def _states(text: str, end_s: float = 60.0, seed: int = 1) -> list[tuple[float, LinkState]]:
    return [(s.at_s, s.state) for s in schedule(parse_profile(text), end_s, random.Random(seed))]


def test_the_named_profiles_have_their_documented_numbers() -> None:
    assert set(PROFILES) >= {
        "clean",
        "wifi-good",
        "wifi-bad",
        "wifi-bursty",
        "dead-zone-12s",
        "roam",
        "congested-2mbit",
        "flapping",
    }
    assert _states("wifi-good") == [(0.0, LinkState(loss_up_pct=1.0, loss_down_pct=1.0))]
    assert _states("wifi-bad") == [(0.0, LinkState(loss_up_pct=15.0, loss_down_pct=15.0))]
    assert _states("congested-2mbit") == [(0.0, LinkState(rate_kbit=2000))]
    assert _states("dead-zone-12s") == [
        (0.0, CLEAN),
        (LEAD_S, LinkState(dead=True)),
        (LEAD_S + 12.0, CLEAN),
    ]
    assert _states("roam") == [(0.0, CLEAN), (15.0, LinkState(subnet=1))]


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("loss-5", [(0.0, LinkState(loss_up_pct=5.0, loss_down_pct=5.0))]),
        ("loss-2.5-0", [(0.0, LinkState(loss_up_pct=2.5))]),
        ("dead-zone-3s-at-4s", [(0.0, CLEAN), (4.0, LinkState(dead=True)), (7.0, CLEAN)]),
        # one way only: the robot's commands lost, its readings arriving (and the other way)
        (
            "dead-zone-down-3s",
            [(0.0, CLEAN), (10.0, LinkState(loss_down_pct=100.0)), (13.0, CLEAN)],
        ),
        (
            "dead-zone-up-2s-at-5s",
            [(0.0, CLEAN), (5.0, LinkState(loss_up_pct=100.0)), (7.0, CLEAN)],
        ),
        ("rate-500kbit", [(0.0, LinkState(rate_kbit=500))]),
        ("rate-10mbit", [(0.0, LinkState(rate_kbit=10000))]),
        ("roam-at-2.5s", [(0.0, CLEAN), (2.5, LinkState(subnet=1))]),
    ],
)
def test_parametrised_profiles(text: str, expected: list[tuple[float, LinkState]]) -> None:
    assert _states(text) == expected
    assert parse_profile(text).name == text  # the name it prints is the one given


@pytest.mark.parametrize(
    "text", ["lossy", "loss-101", "dead-zone-0s", "dead-zone-left-3s", "rate-2gbit", "roam-at-0s"]
)
def test_a_bad_profile_is_refused_with_the_choices(text: str) -> None:
    with pytest.raises(ValueError) as info:
        parse_profile(text)
    assert "wifi-good" in str(info.value) or "must" in str(info.value) or "after" in str(info.value)


def test_assignments_name_robots_or_everyone() -> None:
    robots = ["robot1", "robot2", "robot3"]
    got = parse_assignments(["robot1=dead-zone-12s", "wifi-bad"], robots)
    assert [got[r].name for r in robots] == ["dead-zone-12s", "wifi-bad", "wifi-bad"]
    assert parse_assignments([], robots)["robot2"].name == "clean"
    with pytest.raises(ValueError, match="no robot 'robot9'"):
        parse_assignments(["robot9=wifi-bad"], robots)


def test_a_flapping_link_is_down_for_its_down_time_every_period() -> None:
    states = _states("flap-1s-4s", end_s=16.0)
    assert states == [
        (0.0, CLEAN),
        (9.0, LinkState(dead=True)),  # 5 s clean lead, then up for 4 s first
        (10.0, CLEAN),
        (14.0, LinkState(dead=True)),
        (15.0, CLEAN),
    ]


def test_bursts_alternate_with_the_configured_mean_stays_and_loss() -> None:
    burst = GilbertElliott(good_s=2.0, bad_s=0.5, bad_loss_pct=60.0)
    steps = schedule(bursty(1.0, burst), 20_000.0, random.Random(7))
    good = LinkState(loss_up_pct=1.0, loss_down_pct=1.0)
    bad = LinkState(loss_up_pct=60.0, loss_down_pct=60.0)
    assert steps[0].state == good and {s.state for s in steps} == {good, bad}
    stays: dict[LinkState, list[float]] = {good: [], bad: []}
    for step, after in itertools.pairwise(steps):
        assert step.state != after.state  # every step is a change
        stays[step.state].append(after.at_s - step.at_s)
    assert min(stays[bad]) >= MIN_DWELL_S - 1e-6
    assert sum(stays[good]) / len(stays[good]) == pytest.approx(2.0, rel=0.1)
    assert sum(stays[bad]) / len(stays[bad]) == pytest.approx(0.5, rel=0.1)
    # the same seed draws the same bursts
    assert schedule(bursty(1.0, burst), 100.0, random.Random(7)) == [
        s for s in steps if s.at_s < 100.0
    ]


def test_a_schedule_stops_at_its_end() -> None:
    assert [s.at_s for s in schedule(dead_zone(5.0, at_s=10.0), 12.0, random.Random(0))] == [
        0.0,
        10.0,
    ]


def test_link_states_are_checked() -> None:
    for bad in ({"loss_up_pct": -1}, {"loss_down_pct": 100.5}, {"subnet": 2}, {"rate_kbit": 0}):
        with pytest.raises(ValueError):
            LinkState(**bad)  # type: ignore[arg-type]
    assert LinkState(dead=True).describe().startswith("DEAD")
    assert CLEAN.describe() == "clean, AP 0"
