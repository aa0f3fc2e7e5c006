"""The fleet's promise on real kernel links (issue 39): the CEDDP and two robots in the lab's
namespaces, robot1's link faulted (dead zones shorter and longer than Zenoh's lease, roaming to
another subnet, 15 % loss each way, bursts, a flapping link), robot2's clean. Every run must
reconcile exactly in both directions (every sensor sample of every topic received once or
reported lost; every Hello hop written for robot1 delivered, expired or lost), and a robot back
from a session it lost must be the same incarnation, its absence one outage.

The sensors run KEEP_ALL + TRANSIENT_LOCAL, the profile a fleet uses to lose nothing across
server restarts, and the one with which a dead zone longer than the lease delivered samples
twice (14 331 sent, 17 218 received).

The suite runs one case per kind of fault, each on another link type (``CI_CASES``); the whole
matrix, every fault on every link, is ``ARPZ_LAB_MATRIX=1 python -m pytest -n 2
tests/integration/test_lab_faults.py`` (about 10 minutes). Root only (tests/lab_support.py).
"""

from __future__ import annotations

import itertools
import os
from pathlib import Path
from typing import Any

import pytest

from arpz.lab import Lab, parse_profile
from arpz.lab.fleet import LabRunOptions, lab_spec, run_fleet_in_lab
from arpz.tools.demo import DemoOptions
from tests.lab_support import require_lab

# mostly_idle: a light fleet (two robots' sensors at their preset rates) waiting out its faults
# (tests/conftest.py, share_of): it runs beside the cpu_exclusive tests, as a unit test does,
# whose one process takes more CPU than this fleet
pytestmark = [pytest.mark.integration, pytest.mark.slow, pytest.mark.mostly_idle]

#: seconds of clean link after the last fault: the robot is back and the gap settles
AFTER_S = 8.0
#: dead zones that end the Zenoh session (longer than its 10 s lease)
SESSION_ENDING = ("dead-zone-12s-at-5s", "dead-zone-30s-at-5s")
FAULTS = (
    "dead-zone-3s-at-5s",
    *SESSION_ENDING,
    "roam-at-5s",
    "loss-15",
    "wifi-bursty",
    "flap-1s-4s",
)
LINKS = ("tcp", "tls", "udp", "quic")
#: every kind of fault once, across the link types
CI_CASES = (
    ("tcp", "dead-zone-12s-at-5s"),
    ("tls", "roam-at-5s"),
    ("udp", "loss-15"),
    ("quic", "dead-zone-3s-at-5s"),
    ("udp", "wifi-bursty"),
    ("tcp", "flap-1s-4s"),
)
CASES = (
    list(itertools.product(LINKS, FAULTS))
    if os.environ.get("ARPZ_LAB_MATRIX") == "1"
    else list(CI_CASES)
)
DURABLE = {
    "reliability": "reliable",
    "history": "keep_all",
    "durability": "transient_local",
    "max_samples": 5000,
}


def _duration_s(fault: str) -> float:
    profile = parse_profile(fault)
    last = max(phase.at_s for phase in profile.phases)
    if fault.startswith("dead-zone-"):
        last += float(fault.split("-")[2].rstrip("s"))
    return max(last, 10.0) + AFTER_S


@pytest.mark.parametrize(("link", "fault"), CASES)
def test_a_faulted_link_reconciles_both_ways_and_delivers_nothing_twice(
    tmp_path: Path, link: str, fault: str
) -> None:
    require_lab()
    options = LabRunOptions(
        robots=2,
        link=link,
        duration_s=_duration_s(fault),
        profiles=(f"robot1={fault}",),
        demo=DemoOptions(rate_hz=20.0, hello_rate_hz=10.0),
    )
    with Lab.create(options.robot_names) as lab:
        spec = lab_spec(options, lab, tmp_path)
        spec.ceddp["sensor_qos"] = DURABLE
        spec.ceddp["summary_period_s"] = 1.0
        for conf in spec.robots.values():
            conf["sensor_qos"] = DURABLE
        result = run_fleet_in_lab(
            lab,
            spec,
            tmp_path,
            profiles={"robot1": parse_profile(fault)},
            duration_s=options.duration_s,
        )
        timeline = list(lab.timeline.entries)
    summary = result.summary
    assert result.problems == [], (result.problems, summary["events"][-10:])
    for robot in ("robot1", "robot2"):
        row = summary["robots"][robot]
        assert len(row["incarnations"]) == 1, (robot, row["incarnations"])
        for name, topic in _sensor_topics(row).items():
            # sent == received + lost with lost >= 0: nothing was received twice
            assert topic["sent"] == topic["received"] + topic["lost"], (robot, name, topic)
            assert topic["decode_errors"] == topic["implausible_lost"] == 0, (robot, name, topic)
    for robot in ("robot1", "robot2"):
        # one host, one clock: the true offset is 0, and the estimate holds under the fault
        # (issue 39: +50 to +274 ms at 15 % loss over TCP and TLS before the NTP-style filter)
        clock = summary["robots"][robot]["clock"]
        assert clock is not None and abs(clock["offset_ms"]) < 5.0, (robot, clock)
    faulted = summary["robots"]["robot1"]
    hello = faulted["downlink"]["hello"]
    assert hello["reconciled"] is True, hello
    assert faulted["hello"]["received"] > 0, faulted["hello"]
    if fault in SESSION_ENDING:
        # back as the same incarnation: one outage, its matches resumed
        assert len(faulted["outages_s"]) == 1, (faulted["outages_s"], summary["events"])
        assert (faulted["joins"], faulted["leaves"]) == (2, 2), summary["events"]
    elif fault.startswith("dead-zone-3s"):
        assert faulted["outages_s"] == [] and faulted["leaves"] == 1, summary["events"]
    elif fault.startswith("roam"):
        # the robot sees its own address change and reopens its session at once (0.3-0.5 s
        # over every link): the CEDDP may not even see it go; if it does, it is one outage
        assert len(faulted["outages_s"]) <= 1, (faulted["outages_s"], summary["events"])
    # the fault was real: frames dropped by the kernel, or the robot on the other subnet
    counters = result.counters["robot1"]
    if fault.startswith("roam"):
        moved = [e for e in timeline if e.get("robot") == "robot1" and e.get("subnet") == 1]
        assert moved, timeline
    else:
        assert counters.up_dropped + counters.down_dropped > 0, counters


def _sensor_topics(row: dict[str, Any]) -> dict[str, dict[str, Any]]:
    return {name: t for name, t in row["topics"].items() if name != "hello"}
