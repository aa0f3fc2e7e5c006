"""docs/deploy.md followed literally on loopback (issue 15, item 6).

The certificates are made by the guide's command, the configs are deploy/'s files with the
guide's edits applied as written (delete the `listen`/`connect` line, uncomment `zenoh_config`,
copy `traces/`), `/etc/arpz` is a temporary directory and the server's address is 127.0.0.1 on
a free port. The fleet must connect over mutual TLS, deliver every sample, and relay its Hellos
through robot 3 as the example config says.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from tests.integration.fleet import Process, free_port
from tests.support import wait_until

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[2]
DEPLOY = ROOT / "deploy"


def follow_the_guide(etc: Path, port: int) -> None:
    """Sections 1-3 of docs/deploy.md, with /etc/arpz = ``etc``."""
    fleet_dir = etc.parent / "fleet-lab"
    # section 3: the certificates, by the guide's command (server address: this machine)
    subprocess.run(
        [sys.executable, str(DEPLOY / "tls" / "make_fleet_certs.py"), "--out", str(fleet_dir),
         "--fleet", "lab", "--server-ip", "127.0.0.1", "--server-name", "localhost",
         "--paths-on-hosts", str(etc / "tls"), "--operator", "operator",
         "robot1", "robot2", "robot3"],
        check=True, capture_output=True, timeout=120,
    )  # fmt: skip
    (etc / "tls").mkdir(parents=True)
    (etc / "zenoh").mkdir()
    for name in ("ca.pem", "ceddp.pem", "ceddp.key", "robot1.pem", "robot1.key", "robot3.pem",
                 "robot3.key"):  # fmt: skip
        shutil.copy(fleet_dir / name, etc / "tls" / name)
    for name in ("ceddp-router.json5", "robot1-client.json5", "robot3-client.json5"):
        text = (fleet_dir / "zenoh" / name).read_text()
        # the one deviation: a free port instead of 7447, so tests never collide
        (etc / "zenoh" / name).write_text(text.replace(":7447", f":{port}"))
    # sections 1 and 2: the example TOMLs, edited as the guide says
    var = etc.parent / "var"
    var.mkdir()
    ceddp = (DEPLOY / "ceddp.toml").read_text()
    ceddp = _delete_line(ceddp, 'listen = ["tcp/0.0.0.0:7447"]')
    ceddp = _uncomment(ceddp, 'zenoh_config = "/etc/arpz/zenoh/ceddp-router.json5"')
    (etc / "ceddp.toml").write_text(_local(ceddp, etc, var))
    for robot in ("robot1", "robot3"):
        text = (DEPLOY / f"{robot}.toml").read_text()
        text = _delete_line(text, 'connect = ["tcp/192.168.1.10:7447"]')
        text = _uncomment(text, f'zenoh_config = "/etc/arpz/zenoh/{robot}-client.json5"')
        # the relay outlives the origin: robot 1's Hellos always have robot 3 to go round
        duration_s = 14 if robot == "robot3" else 6
        (etc / f"{robot}.toml").write_text(f"duration_s = {duration_s}\n" + _local(text, etc, var))
    shutil.copytree(DEPLOY / "traces", etc / "traces")


def _delete_line(text: str, line: str) -> str:
    lines = text.splitlines()
    found = [i for i, x in enumerate(lines) if x.split("#")[0].strip() == line]
    assert len(found) == 1, f"the guide says to delete {line!r}: not found once"
    del lines[found[0]]
    return "\n".join(lines) + "\n"


def _uncomment(text: str, line: str) -> str:
    commented = f"# {line}"
    assert text.count(commented) == 1, f"the guide says to uncomment {line!r}: not found once"
    return text.replace(commented, line)


def _local(text: str, etc: Path, var: Path) -> str:
    return text.replace("/etc/arpz", str(etc)).replace("/var/lib/arpz", str(var))


def test_the_deploy_guide_works_when_followed_literally(tmp_path: Path) -> None:
    etc = tmp_path / "etc-arpz"
    port = free_port()
    follow_the_guide(etc, port)
    server = Process("ceddp", ["-m", "arpz.ceddp", "--config", str(etc / "ceddp.toml")], tmp_path)
    try:
        # robots over QUIC with mutual TLS (the recommended link), TLS over TCP beside it
        server.wait_for(f"ready on quic/0.0.0.0:{port},tls/0.0.0.0:{port}", timeout_s=60)
        robots: list[Process] = []
        try:
            for robot in ("robot3", "robot1"):  # the Hello relay first
                robots.append(
                    Process(robot, ["-m", "arpz.robot", "--config", str(etc / f"{robot}.toml")],
                            tmp_path)
                )  # fmt: skip
                wait_until(
                    lambda robot=robot: f"robot {robot} joined" in server.output(),  # type: ignore[misc]
                    timeout_s=60,
                    what=f"{robot} to join over QUIC with mutual TLS",
                )
            for proc in robots:
                assert proc.popen.wait(timeout=60) == 0, proc.output()
        finally:
            for proc in robots:
                proc.kill()
        # each robot's final report goes before its presence does: once both are seen gone,
        # the CEDDP has what the summary below reconciles
        wait_until(
            lambda: all(f"robot {robot} left" in server.output() for robot in ("robot1", "robot3")),
            timeout_s=30,
            what="the CEDDP to see both robots leave",
        )
        assert server.interrupt() == 0, server.output()  # SIGINT: what systemctl stop sends
    finally:
        server.kill()
    summaries = sorted((tmp_path / "var").glob("summary*.json"))
    assert summaries, list((tmp_path / "var").iterdir())
    summary = json.loads(summaries[-1].read_text())
    for robot in ("robot1", "robot3"):
        record = summary["robots"][robot]
        assert record["final_stats"], robot
        for topic, t in record["topics"].items():
            if topic == "hello":
                continue
            assert t["received"] == t["sent"] > 0 and t["lost"] == 0, (robot, topic, t)
    assert "front_sonar" in summary["robots"]["robot1"]["topics"]  # the replayed trace ran
    hello = summary["robots"]["robot1"]["hello"]
    # Hellos go round through robot 3; any sent before the CEDDP saw robot 3 are dropped and
    # counted (no_relay), and robot 1 counts them lost: none vanish
    assert hello["received"] > 0 and hello["sent"] == hello["received"] + hello["lost"], hello
    assert summary["hello_relay"]["no_relay"] <= hello["lost"] <= 5, (hello, summary["hello_relay"])
