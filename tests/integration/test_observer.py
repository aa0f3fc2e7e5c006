"""The observer identity of docs/deploy.md on a secured fleet, both sides (issue 41).

A real CEDDP router with the mutual TLS and access control that deploy/tls/make_fleet_certs.py
makes (real openssl certificates), a real robot, and the tools run as processes holding the
``--observer`` certificate: ``topic list``, ``topic echo``, ``topic hz``, ``topic delay``,
``record`` and ``doctor`` work; ``topic echo --reliable`` is refused with the reason. The same
certificate's attempts to put a sensor sample on the robot's keys and to command the robot,
plainly and through the reliable channel, reach nobody: neither the CEDDP (its summary) nor a
subscriber of those keys (another observer session, and one holding the robot's own
certificate), while the real samples and the CEDDP's commands on the same keys do reach them
(the positive controls).
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
from pathlib import Path
from typing import Any

import msgspec
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory

from arpz.channel import Writer
from arpz.core.messages import (
    DECODE_ERRORS,
    STATS_DECODER,
    Command,
    RobotStats,
    Sample,
    encode,
)
from arpz.core.traffic import COMMAND_QOS, SENSOR_QOS
from tests.integration.fleet import robots, settle
from tests.integration.secure_fleet import (
    client_config,
    make_fleet_tls,
    open_client,
    secure_ceddp,
    write_secure_robot,
)
from tests.support import wait_until

pytestmark = pytest.mark.integration
FLEET = "obs"
R1 = f"arpz/{FLEET}/robot/robot1"
#: machine1's sensors and their ROS 2 types (arpz/core/config.py presets); its IMU reading
#: changes at every read, so the local cache holds none back and it goes at the preset's rate
SENSORS = {
    "dht11": "sensor_msgs/msg/Temperature",
    "flame": "std_msgs/msg/Bool",
    "imu": "sensor_msgs/msg/Imu",
    "lidar": "sensor_msgs/msg/LaserScan",
    "light": "sensor_msgs/msg/Illuminance",
    "pir": "std_msgs/msg/Bool",
}
RATE_HZ = 20
FORGED_WRITER = "robot1:00000forged0"
FORGED_COMMANDER = "ceddp:forged"


def tool(tls: Path, endpoint: str, *args: str, timeout_s: float = 60) -> tuple[int, str, str]:
    """``python -m arpz ARGS`` with the observer's certificate; (exit code, stdout, stderr)."""
    done = subprocess.run(
        [
            sys.executable, "-m", "arpz", *args, "--connect", endpoint, "--fleet", FLEET,
            "--zenoh-config", str(client_config(tls, "operator")),
        ],
        capture_output=True, text=True, timeout=timeout_s,
    )  # fmt: skip
    return done.returncode, done.stdout, done.stderr


def json_lines(text: str) -> list[dict[str, Any]]:
    return [json.loads(line) for line in text.splitlines() if line.startswith("{")]


class Watch:
    """Decoded samples and commands a subscriber got, by key, from Zenoh's threads."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.by_writer: dict[str, list[str]] = {}

    def __call__(self, key: str, payload: bytes, _att: bytes | None) -> None:
        try:
            writer = msgspec.msgpack.decode(payload)[0]
        except (*DECODE_ERRORS, TypeError, IndexError, KeyError):
            writer = "?"
        with self._lock:
            self.by_writer.setdefault(str(writer), []).append(key)

    def writers(self) -> set[str]:
        with self._lock:
            return set(self.by_writer)

    def keys_of(self, prefix: str) -> list[str]:
        with self._lock:
            return [k for w, ks in self.by_writer.items() if w.startswith(prefix) for k in ks]


class Reports:
    """The robot's reports on its stats key, as any subscriber of the fleet gets them."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._stats: list[RobotStats] = []

    def __call__(self, _key: str, payload: bytes, _att: bytes | None) -> None:
        stats = STATS_DECODER.decode(payload)
        with self._lock:
            self._stats.append(stats)

    def final(self) -> RobotStats:
        with self._lock:
            finals = [s for s in self._stats if s.final]
        assert len(finals) == 1, "the robot's final report"
        return finals[0]


def _forge(session: Any) -> None:
    """Everything an observer might try: plain puts of a sample and a command, and the same
    through reliable-channel writers (a token, DATA and heartbeats), on an existing topic and
    on a new one."""
    sample = encode(Sample(FORGED_WRITER, 1, 1, 999.0))
    command = encode(Command(FORGED_COMMANDER, 1, 1, [9.0, 9.0]))
    session.put(f"{R1}/sensor/imu", sample)
    session.put(f"{R1}/sensor/forged", sample)
    session.put(f"{R1}/cmd/velocity", command)
    session.put(f"{R1}/cmd/hello", command)
    for key, qos, payload in (
        (f"{R1}/sensor/forged2", SENSOR_QOS, sample),
        (f"{R1}/cmd/velocity", COMMAND_QOS, command),
    ):
        with Writer(session, key, qos) as writer:
            for _ in range(3):
                writer.write(payload)
            settle(0.3)  # deliberately: heartbeats go out while no reader matches


def test_the_observer_can_observe_and_nothing_more(tmp_path: Path) -> None:
    tls = make_fleet_tls(tmp_path / "tls", FLEET, ["robot1"], observers=("operator",))
    with secure_ceddp(tmp_path, tls, fleet=FLEET) as (server, endpoint):
        config = write_secure_robot(
            tmp_path, "robot1", endpoint, client_config(tls, "robot1"),
            fleet=FLEET, preset="machine1", rate_hz=RATE_HZ, hello=True,
        )  # fmt: skip
        watch, robot_side, reports = Watch(), Watch(), Reports()
        with (
            robots(tmp_path, [config]) as procs,
            open_client(endpoint, client_config(tls, "operator")) as observer,
            open_client(endpoint, client_config(tls, "operator")) as watcher,
            open_client(endpoint, client_config(tls, "robot1")) as robot1_session,
        ):
            wait_until(lambda: "robot robot1 joined" in server.output(), what="robot1 joined")
            watcher.subscribe(f"{R1}/sensor/*", watch)
            watcher.subscribe(f"{R1}/cmd/*", watch)
            watcher.subscribe(f"{R1}/stats", reports)
            robot1_session.subscribe(f"{R1}/cmd/*", robot_side)

            # --- what the observer can do ------------------------------------------------
            code, out, err = tool(tls, endpoint, "topic", "list", "--json")
            assert code == 0, err
            graph = json.loads(out)
            assert {(n["name"], n["alive"], n["mode"]) for n in graph["nodes"]} == {
                ("ceddp", True, "channel"),
                ("robot1", True, "channel"),
            }
            types = {t["name"]: t["type"] for t in graph["topics"]}
            assert {f"/robot1/{name}": t for name, t in SENSORS.items()}.items() <= types.items()

            code, out, err = tool(
                tls, endpoint, "topic", "echo", "/robot1/imu", "--count", "3",
                "--duration", "10", "--json",
            )  # fmt: skip
            assert code == 0, err
            lines = json_lines(out)
            assert len(lines) == 4 and lines[-1]["counters"]["delivered"] == 3, out
            assert all(8 < m["message"]["value"] < 12 for m in lines[:3])
            assert "BEST_EFFORT" in err

            code, out, err = tool(
                tls, endpoint, "topic", "hz", "/robot1/imu", "--duration", "3", "--json"
            )
            assert code == 0, err
            final = json_lines(out)[-1]
            assert final["final"] and 0.7 * RATE_HZ <= final["rate_hz"] <= 1.3 * RATE_HZ, final

            code, out, err = tool(
                tls, endpoint, "topic", "delay", "/robot1/imu", "--duration", "2", "--json"
            )
            assert code == 0, err
            final = json_lines(out)[-1]
            assert final["corrected"] and "this host not measured" not in final["clock"], final

            code, _, err = tool(
                tls, endpoint, "topic", "echo", "/robot1/imu", "--reliable",
                "--duration", "2",
            )  # fmt: skip
            assert code == 2 and "access control in force" in err and "--reliable" in err, err

            out_file = tmp_path / "observed.mcap"
            code, out, err = tool(
                tls, endpoint, "record", "--out", str(out_file), "--duration", "4", "--json"
            )
            assert code == 0, err
            summary = json.loads(out)
            assert summary["read_only"] and summary["mode"] == "channel", summary
            assert "access control in force" in err
            for name in SENSORS:
                # the local cache holds unchanged readings back: a few per second at least
                assert summary["topics"][f"/robot1/{name}"]["messages"] >= 2, (name, summary)
            assert summary["topics"]["/robot1/arpz/presence"]["messages"] == 1
            assert summary["topics"]["/robot1/arpz/announce"]["messages"] >= 1
            with out_file.open("rb") as stream:  # a ROS 2 reader takes the whole file
                reader = make_reader(stream, decoder_factories=[DecoderFactory()])
                decoded = sum(1 for _ in reader.iter_decoded_messages())
            assert decoded == summary["messages"]

            code, out, err = tool(tls, endpoint, "doctor", "--json", "-")
            assert code == 0, out + err
            checks = {c["check"]: c["level"] for c in json.loads(out)["checks"]}
            assert checks["robots"] == checks["access control"] == "OK", checks

            # --- and nothing more: its puts reach nobody ---------------------------------
            _forge(observer)
            # the positive controls on the same subscriptions: the robot's real samples and the
            # CEDDP's Hello commands arrive
            wait_until(
                lambda: watch.keys_of("robot1:") and watch.keys_of("ceddp:"),
                what="the real samples and commands at the watcher",
            )
            wait_until(lambda: robot_side.keys_of("ceddp:"), what="robot1 to get its Hellos")
            settle(1.5)  # deliberately: time for a forged message to arrive, were it let through
            assert procs[0].interrupt() == 0, procs[0].output()
            robot_out = procs[0].output()
        assert server.interrupt() == 0, server.output()

    assert FORGED_WRITER not in watch.writers() and FORGED_COMMANDER not in watch.writers()
    assert FORGED_COMMANDER not in robot_side.writers()
    assert "undecodable command" not in robot_out
    summary = json.loads((tmp_path / "summary.json").read_text())
    robot1 = summary["robots"]["robot1"]
    assert not {"forged", "forged2"} & set(robot1["topics"]), robot1["topics"].keys()
    imu = robot1["topics"]["imu"]
    # nothing but the robot's own samples was counted on its topic
    assert imu["received"] == imu["sent"] > 0 and imu["decode_errors"] == 0
    # the robot's own final report: its Hello commands arrived, nothing else, nothing undecodable
    final = reports.final()
    assert final.commands_received > 0 and final.command_decode_errors == 0
    assert set(final.inbound) <= {"cmd/hello", "ceddp/qos"}, final.inbound
