"""A robot with a camera (640x480 RGB, 921 600-byte frames) and a 1 MB point cloud, as real
processes, over a UDP link that loses 5 % of its 1500-byte radio frames, to a real CEDDP.

Shared memory is off on every session (on one host Zenoh would otherwise carry the frames
outside the emulated link), and the proxy's byte counters must show that the frames' bytes
crossed it. Every frame the robot sent is received or counted lost at the CEDDP.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from arpz.core.messages import CEDDP_STATS_DECODER
from arpz.netem.process import netem_process
from arpz.transport.zenoh import ZenohTransport
from tests.integration.fleet import Process, robots
from tests.support import client, free_port, free_udp_port, wait_until

# a camera's frame rate is bounded by the CPU its robot gets (34 frames where 35 were required
# beside an integration test, 28 beside a unit test): runs with the whole machine to itself
# (tests/conftest.py, cpu_share)
pytestmark = [pytest.mark.integration, pytest.mark.cpu_exclusive(whole_machine=True)]

NO_SHM = "{ transport: { shared_memory: { enabled: false } } }\n"
#: the robot's side: no shared memory, and no datagram larger than one radio frame
ROBOT_ZENOH = (
    "{ transport: { shared_memory: { enabled: false }, link: { tx: { batch_size: 1472 } } } }\n"
)
CLEAN_S = 3.0
#: the lossy phase lasts at least LOSSY_S and until the CEDDP ingested LOSSY_FRAMES frames during
#: it (camera and point cloud), within LOSSY_TIMEOUT_S
LOSSY_S = 4.0
LOSSY_FRAMES = 12
LOSSY_TIMEOUT_S = 90.0
CAMERA_BYTES = 640 * 480 * 3
CLOUD_BYTES = 87_381 * 12


def ingested_counter(raw: ZenohTransport) -> Callable[[], int]:
    """The CEDDP's count of samples ingested, as its latest stats report says (0 before one)."""
    latest = [0]

    def on_stats(_key: str, payload: bytes, _att: bytes | None) -> None:
        latest[0] = CEDDP_STATS_DECODER.decode(payload).processed

    raw.subscribe("arpz/itest/ceddp/stats", on_stats)
    return lambda: latest[0]


def test_camera_frames_and_point_clouds_cross_a_lossy_link_and_reconcile(tmp_path: Path) -> None:
    udp, tcp, proxy = free_udp_port(), free_port(), free_udp_port()
    (tmp_path / "ceddp.json5").write_text(NO_SHM)
    (tmp_path / "robot.json5").write_text(ROBOT_ZENOH)
    (tmp_path / "ceddp.toml").write_text(
        f'fleet = "itest"\nlisten = ["udp/127.0.0.1:{udp}", "tcp/127.0.0.1:{tcp}"]\n'
        f'zenoh_config = "{tmp_path / "ceddp.json5"}"\n'
        f'rrd = "{tmp_path / "ceddp.rrd"}"\nsummary_json = "{tmp_path / "summary.json"}"\n'
        "metrics_period_s = 0.2\n"
    )
    robot = tmp_path / "robot1.toml"
    robot.write_text(
        f'robot_id = "robot1"\nfleet = "itest"\nconnect = ["udp/127.0.0.1:{proxy}"]\n'
        f'zenoh_config = "{tmp_path / "robot.json5"}"\nstats_period_s = 0.2\n'
        '[[sensors]]\nname = "front"\nkind = "camera"\nrate_hz = 10.0\n'
        '[[sensors]]\nname = "scan3d"\nkind = "pointcloud"\nrate_hz = 5.0\n'
    )
    server = Process(
        "ceddp", ["-m", "arpz.ceddp", "--config", str(tmp_path / "ceddp.toml")], tmp_path
    )
    try:
        server.wait_for("ready on")
        with netem_process(
            f"udp/127.0.0.1:{proxy}",
            f"udp/127.0.0.1:{udp}",
            *("--loss", "5", "--per-frame", "--clean-s", str(CLEAN_S), "--seed", "11"),
        ) as netem:
            with robots(tmp_path, [robot]) as procs, client(f"tcp/127.0.0.1:{tcp}") as raw:
                processed = ingested_counter(raw)
                wait_until(lambda: "robot robot1 joined" in server.output(), what="robot1 joined")
                # deliberately: the link turns lossy after CLEAN_S; it stays so for LOSSY_S and
                # until LOSSY_FRAMES frames have arrived through it (a slow host's camera is slow)
                time.sleep(CLEAN_S)
                lossy_from = processed()
                time.sleep(LOSSY_S)
                wait_until(
                    lambda: processed() - lossy_from >= LOSSY_FRAMES,
                    timeout_s=LOSSY_TIMEOUT_S,
                    what=f"{LOSSY_FRAMES} frames over the lossy link",
                )
                assert procs[0].interrupt(timeout_s=30) == 0, procs[0].output()
            report = netem.stop()
        assert server.interrupt(timeout_s=60) == 0, server.output()
    finally:
        server.kill()
    summary = json.loads((tmp_path / "summary.json").read_text())
    row = summary["robots"]["robot1"]
    assert row["final_stats"], "the robot's final report did not arrive"
    camera, cloud = row["topics"]["front"], row["topics"]["scan3d"]
    for topic in (camera, cloud):
        assert topic["sent"] == topic["received"] + topic["lost"], topic
        assert topic["oversize"] == topic["decode_errors"] == topic["implausible_lost"] == 0
    # frames arrive over a 5 % link: only a frame still incomplete when the next one is written
    # is dropped (KEEP_LAST 1 frame: the newest frame wins), and it is counted lost. How many
    # are dropped depends on the CPU the processes get (29 of 52 arrived once with two other
    # test processes on the 2 cores, under the 60 % this test asked before): the delivery is
    # benchmarks/large_messages.py's, this test asks for a third and the reconciliation above
    # the robot's camera rate is its CPU's (28, 34 and 16 of 70 frames in 7 s on a VM slowed
    # fourfold by a neighbour, even with the machine to itself): the lossy phase lasts until
    # LOSSY_FRAMES have arrived through it, whatever the rate
    assert camera["sent"] + cloud["sent"] >= LOSSY_FRAMES
    assert camera["received"] >= camera["sent"] / 3
    assert cloud["received"] >= cloud["sent"] / 3 > 0
    assert camera["retransmitted"] > 0, "the link lost fragments: some were resent"
    # the CEDDP's reassembly accounts for every frame it delivered to ingest and every one it
    # dropped: together they are what arrived or was counted lost
    frames = summary["ingest"]["frames"]["frames"]
    assert frames["frames_delivered"] == camera["received"] + cloud["received"], frames
    assert frames["bad_fragments"] == frames["frames_too_large"] == 0, frames
    dropped = frames["frames_dropped_incomplete"] + frames["frames_dropped_over_limit"]
    assert dropped <= camera["lost"] + cloud["lost"], (frames, camera["lost"], cloud["lost"])
    assert report is not None
    up = report["up"]
    print(
        f"\ncamera {camera['received']}/{camera['sent']} frames (lost {camera['lost']}, "
        f"p50 {camera['latency_ms_p50']:.0f} ms, p99 {camera['latency_ms_p99']:.0f} ms), "
        f"point cloud {cloud['received']}/{cloud['sent']}; fragments resent "
        f"{camera['retransmitted'] + cloud['retransmitted']}; link: {up['bytes_out']} bytes out, "
        f"{up['dropped_loss']} of {up['received']} datagrams lost"
    )
    crossed = camera["received"] * CAMERA_BYTES + cloud["received"] * CLOUD_BYTES
    assert up["bytes_out"] >= crossed, (up, crossed)  # through the link, not shared memory
    assert up["largest_datagram"] <= 1472
    assert up["dropped_loss"] > 0


def test_over_tcp_a_robot_cuts_frames_into_stream_sized_fragments(tmp_path: Path) -> None:
    """A robot whose link is TCP needs no radio-frame fragments (TCP resends its own segments):
    it picks 60 KiB ones by itself, 48 times fewer channel samples per frame than the 1280 B of
    a UDP link, and the CEDDP reassembles them from their headers without being told."""
    tcp = free_port()
    (tmp_path / "nosh.json5").write_text(NO_SHM)
    (tmp_path / "ceddp.toml").write_text(
        f'fleet = "itest"\nlisten = ["tcp/127.0.0.1:{tcp}"]\n'
        f'zenoh_config = "{tmp_path / "nosh.json5"}"\n'
        f'rrd = "{tmp_path / "ceddp.rrd"}"\nsummary_json = "{tmp_path / "summary.json"}"\n'
    )
    robot = tmp_path / "robot1.toml"
    robot.write_text(
        f'robot_id = "robot1"\nfleet = "itest"\nconnect = ["tcp/127.0.0.1:{tcp}"]\n'
        f'zenoh_config = "{tmp_path / "nosh.json5"}"\nstats_period_s = 0.2\n'
        '[[sensors]]\nname = "front"\nkind = "camera"\nrate_hz = 10.0\n'
    )
    server = Process(
        "ceddp", ["-m", "arpz.ceddp", "--config", str(tmp_path / "ceddp.toml")], tmp_path
    )
    try:
        server.wait_for("ready on")
        with robots(tmp_path, [robot]) as procs:
            wait_until(lambda: "robot robot1 joined" in server.output(), what="robot1 joined")
            time.sleep(3.0)  # deliberately: about 30 frames
            assert procs[0].interrupt(timeout_s=30) == 0, procs[0].output()
        assert server.interrupt(timeout_s=60) == 0, server.output()
    finally:
        server.kill()
    summary = json.loads((tmp_path / "summary.json").read_text())
    camera = summary["robots"]["robot1"]["topics"]["front"]
    assert camera["sent"] == camera["received"] + camera["lost"] and camera["received"] > 5, camera
    frames = summary["ingest"]["frames"]["frames"]
    assert frames["frames_delivered"] == camera["received"], frames
    # a frame is the encoded LargeSample: the image and a few dozen bytes of header
    frame_bytes = frames["bytes_delivered"] / frames["frames_delivered"]
    assert CAMERA_BYTES < frame_bytes < CAMERA_BYTES + 200
    per_frame = -(-int(frame_bytes) // (60 * 1024))  # 16 fragments of 60 KiB, against 721 of 1280
    arrived = frames["fragments_received"] - frames["fragments_duplicate"]
    assert arrived <= per_frame * camera["sent"], (frames, camera["sent"])
    assert arrived >= per_frame * camera["received"], (frames, camera["received"])
