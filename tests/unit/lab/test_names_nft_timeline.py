"""The lab's names, its nftables text, its timeline and its availability check: no root needed."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from arpz.core.errors import ArpzError
from arpz.lab import net, nft
from arpz.lab.names import (
    IF_PREFIX,
    IFNAME_MAX,
    MAX_ROBOTS,
    LabNames,
    LabUnavailable,
    check_robot_names,
    lab_id_of_interface,
    lab_id_of_namespace,
    new_lab_id,
    robot_address,
)
from arpz.lab.profiles import LinkState
from arpz.lab.timeline import Timeline, link_states, load, spans


def test_names_are_unique_prefixed_and_fit_the_kernel() -> None:
    ids = {new_lab_id() for _ in range(200)}
    assert len(ids) == 200
    names = LabNames(ids.pop())
    longest = [
        names.robot_if(MAX_ROBOTS),
        names.robot_ap_if(MAX_ROBOTS),
        names.bridge(1),
        names.interface("ca"),
    ]
    assert all(len(n) <= IFNAME_MAX and n.startswith(IF_PREFIX) for n in longest), longest
    assert lab_id_of_interface(names.robot_ap_if(3)) == names.lab_id
    assert lab_id_of_namespace(names.namespace("robot1")) == names.lab_id
    assert names.ap.startswith("arpzlab-") and names.ceddp.endswith("-ceddp")
    # not ours: another tool's namespaces and interfaces
    assert lab_id_of_namespace("arpzrc-123-1-r") is None
    assert lab_id_of_interface("eth0") is None
    with pytest.raises(ValueError):
        LabNames("ABCDEF")
    with pytest.raises(ValueError, match="longer than 15"):
        names.interface("r1000000")


def test_robot_names_and_addresses() -> None:
    check_robot_names(["robot1", "robot-2"])
    for bad in (["robot1", "robot1"], ["ap"], ["Robot"], []):
        with pytest.raises(ValueError):
            check_robot_names(bad)
    assert robot_address(1, 0) == "10.77.1.11"
    assert robot_address(1, 1) == "10.77.2.11"
    with pytest.raises(ValueError):
        robot_address(MAX_ROBOTS + 1, 0)


def test_the_ruleset_counts_and_drops_on_ingress() -> None:
    table = nft.table_ruleset({"up_r1": "azlabcdefr1a"})
    assert 'type filter hook ingress device "azlabcdefr1a" priority filter; policy accept;' in table
    assert "table netdev arpzlab {" in table and "counter up_r1_dropped { }" in table
    loss = nft.chain_update("up_r1", loss_pct=15.0, dead=False)
    assert loss.splitlines() == [
        "flush chain netdev arpzlab up_r1",
        'add rule netdev arpzlab up_r1 counter name "up_r1_seen"',
        'add rule netdev arpzlab up_r1 numgen random mod 1000 < 150 counter name "up_r1_dropped"'
        " drop",
    ]
    dead = nft.chain_update("down_r2", loss_pct=15.0, dead=True)
    assert dead.splitlines()[-1] == (
        'add rule netdev arpzlab down_r2 counter name "down_r2_dropped" drop'
    )
    # 100 % is a dead direction (numgen's values stop at 999: "< 1000" is refused by nft)
    assert nft.chain_update("down_r2", loss_pct=100.0, dead=False) == dead
    clean = nft.chain_update("up_r1", loss_pct=0.0, dead=False)
    assert "drop" not in clean and "flush chain" in clean
    assert nft.permille(0.04) == 0 and nft.permille(0.1) == 1 and nft.permille(100) == 1000


def test_counters_are_read_from_nfts_json() -> None:
    listing = {
        "nftables": [
            {"metainfo": {"version": "1.0.6"}},
            {"counter": {"family": "netdev", "name": "up_r1_seen", "packets": 7, "bytes": 9}},
            {"counter": {"family": "netdev", "name": "up_r1_dropped", "packets": 2, "bytes": 3}},
        ]
    }
    assert nft.parse_counters(listing) == {"up_r1_seen": 7, "up_r1_dropped": 2}


def test_the_timeline_says_when_a_dead_zone_was(tmp_path: Path) -> None:
    seen: list[str] = []
    timeline = Timeline(tmp_path / "t.jsonl", on_event=lambda e: seen.append(e["event"]))
    timeline.record("lab_up", lab_id="abcdef")
    timeline.link("robot1", LinkState(), "phase 1", "10.77.1.11")
    timeline.link("robot2", LinkState(dead=True), "other robot", "10.77.1.12")
    timeline.link("robot1", LinkState(dead=True), "phase 2", "10.77.1.11")
    timeline.link("robot1", LinkState(loss_up_pct=5), "phase 3", "10.77.1.11")
    timeline.link("robot1", LinkState(dead=True), "phase 4", "10.77.1.11")
    entries = load(tmp_path / "t.jsonl")
    assert entries == json.loads(json.dumps(timeline.entries))  # what is on disk is all of it
    assert seen == ["lab_up", "link", "link", "link", "link", "link"]
    t = [e["t"] for e in entries]
    assert t == sorted(t) and all(e["mono"] > 0 and e["wall"] > 1e9 for e in entries)
    dead = spans(entries, "robot1", lambda s: s.dead)
    assert dead == [(t[3], t[4]), (t[5], None)]
    assert spans(entries, "robot1", lambda s: s.dead, clock="mono")[0][0] == entries[3]["mono"]
    assert [s for _, s in link_states(entries, "robot2")] == [LinkState(dead=True)]


def test_missing_names_everything_absent(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(net, "_which", lambda tool: None if tool == "nft" else f"/x/{tool}")
    monkeypatch.setattr(net, "_effective_capabilities", lambda: 1 << net.CAP_SYS_ADMIN)
    problems = net.missing()
    assert problems == [
        "the `nft` command (apt-get install nftables)",
        "CAP_NET_ADMIN (run as root)",
    ]
    with pytest.raises(LabUnavailable) as info:
        net.check_available()
    assert isinstance(info.value, ArpzError)
    assert "nftables" in str(info.value) and "CAP_NET_ADMIN" in str(info.value)
    monkeypatch.setattr(net, "IPRoute", None)
    assert "pyroute2" in net.missing()[0]


def test_the_cli_refuses_a_bad_profile_before_building_anything(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from arpz.lab.__main__ import main

    assert main(["run", "--robots", "1", "--profile", "robot2=wifi-bad"]) == 2
    assert "no robot 'robot2'" in capsys.readouterr().err
    assert main(["run", "--profile", "wifi-awful"]) == 2
    assert "unknown profile 'wifi-awful'" in capsys.readouterr().err
