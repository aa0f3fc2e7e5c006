"""Mutual TLS and access control, through a real CEDDP process and real robot processes.

Everything is proven by what the CEDDP counted (its summary.json), by what the robots report, and
by what clients holding real certificates can see: a client holding robot 2's certificate can
neither publish as robot 1 nor command robot 1 nor read robot 1's traffic, a client without a
fleet certificate cannot connect at all, and the CEDDP still sees everything from the legitimate
robots. Each negative check has a positive control on the same link (the same client doing the
allowed thing), so "nothing arrived" cannot pass because nothing was sent.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from arpz.ceddp.services import ServiceCaller, ServiceRefused
from arpz.channel import Writer
from arpz.core.messages import DECODE_ERRORS, STATS_DECODER, Command, RobotStats, Sample, encode
from arpz.core.protocol import wire
from arpz.core.traffic import SENSOR_QOS
from arpz.core.transport import TransportError
from arpz.tools.service import main as service_main
from arpz.transport.zenoh import ZenohTransport
from tests.integration.fleet import robots, settle
from tests.integration.secure_fleet import (
    SCRIPT,
    client_config,
    make_fleet_tls,
    open_client,
    secure_ceddp,
    write_secure_robot,
)
from tests.integration.service_handlers import SERVICES
from tests.support import wait_until

pytestmark = pytest.mark.integration
ROOT = Path(__file__).resolve().parents[2]
FLEET = "sec"
COMMITTED = ["ceddp-router.json5", "ceddp-router-usrpwd.json5", "robot1-client.json5"]


class Seen:
    """Keys and payloads a subscriber got, from a Zenoh thread, read by the test thread."""

    def __init__(self) -> None:
        self.items: list[tuple[str, bytes]] = []
        self._lock = threading.Lock()

    def __call__(self, key: str, payload: bytes, _att: bytes | None) -> None:
        with self._lock:
            self.items.append((key, payload))

    def seen_keys(self) -> list[str]:
        with self._lock:
            return [k for k, _ in self.items]

    def payloads(self, key: str) -> list[bytes]:
        with self._lock:
            return [p for k, p in self.items if k == key]


def _forge(forger_key_prefix: str) -> dict[str, bytes]:
    """What a client holding robot 2's certificate tries to put as robot 1."""
    return {
        f"{forger_key_prefix}/sensor/pir": b"\xc1 garbage",
        f"{forger_key_prefix}/sensor/forged": encode(Sample("robot1:000000forged", 1, 1, 1.0)),
        f"{forger_key_prefix}/cmd/velocity": encode(Command("ceddp:forged", 1, 1, [9.0, 9.0])),
        f"{forger_key_prefix}/cmd/garbage": b"\xc1 not a command",
        f"{forger_key_prefix}/stats": b"\xc1 not stats",
    }


def _stats(payload: bytes) -> RobotStats | None:
    try:
        return STATS_DECODER.decode(payload)
    except DECODE_ERRORS:
        return None


def _reconciles(summary: dict[str, object], robot: str, *, skip: tuple[str, ...] = ()) -> None:
    record = summary["robots"][robot]  # type: ignore[index]
    assert record["final_stats"], robot
    for topic, t in record["topics"].items():
        if topic == "hello" or topic in skip:
            continue
        assert t["produced"] == t["sent"] + t["held_back"] > 0, (robot, topic, t)
        assert t["received"] == t["sent"] and t["lost"] == 0, (robot, topic, t)
        assert t["decode_errors"] == 0, (robot, topic, t)


def test_the_committed_deploy_configs_are_the_scripts_output(tmp_path: Path) -> None:
    """deploy/zenoh/*.json5 must not drift from the generator the other tests exercise."""
    make_args = [
        "--fleet", "lab", "--server-ip", "192.168.1.10", "--server-name", "ceddp.local",
        "--paths-on-hosts", "/etc/arpz/tls", "--usrpwd", "--operator", "operator",
        "robot1", "robot2", "robot3",
    ]  # fmt: skip
    done = subprocess.run(
        [sys.executable, str(SCRIPT), "--out", str(tmp_path), *make_args],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    for name in COMMITTED:
        made = (tmp_path / "zenoh" / name).read_text()
        committed = (ROOT / "deploy" / "zenoh" / name).read_text()
        assert made == committed, f"re-run make_fleet_certs.py to refresh deploy/zenoh/{name}"
    made = (tmp_path / "zenoh" / "robot1-client-usrpwd.json5").read_text()
    password = (tmp_path / "passwords.txt").read_text().split("robot1:")[1].split("\n")[0]
    committed = (ROOT / "deploy" / "zenoh" / "robot1-client-usrpwd.json5").read_text()
    assert made.replace(password, "CHANGE-ME: the robot1 line of passwords.txt") == committed
    for key in ("ca.key", "ceddp.key", "robot1.key", "passwords.txt"):
        assert (tmp_path / key).stat().st_mode & 0o077 == 0, f"{key} must be private"


def _openssl(*args: str) -> str:
    done = subprocess.run(["openssl", *args], capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr
    return done.stdout + done.stderr


def test_the_script_makes_verifiable_certificates_and_keeps_them_when_robots_are_added(
    tmp_path: Path,
) -> None:
    out = make_fleet_tls(tmp_path, FLEET, ["robot1", "robot2"])
    before = {name: (out / name).read_bytes() for name in ("ca.pem", "ceddp.pem", "robot1.pem")}
    make_fleet_tls(tmp_path, FLEET, ["robot1", "robot2", "robot3"])  # robot3 joins later
    for name, content in before.items():
        assert (out / name).read_bytes() == content, f"{name} was replaced"
    ca = str(out / "ca.pem")
    for robot in ("robot1", "robot2", "robot3"):
        assert ": OK" in _openssl("verify", "-CAfile", ca, str(out / f"{robot}.pem"))
        subject = _openssl("x509", "-noout", "-subject", "-in", str(out / f"{robot}.pem"))
        assert subject.strip().endswith(f"CN = {robot}"), subject
        router = (out / "zenoh" / "ceddp-router.json5").read_text()
        assert f'"cert_common_names": [\n          "{robot}"' in router
    server = _openssl("x509", "-noout", "-ext", "subjectAltName", "-in", str(out / "ceddp.pem"))
    assert "IP Address:127.0.0.1" in server and "DNS:localhost" in server
    # a robot id that is not a key chunk is refused before anything is made
    bad = subprocess.run(
        [sys.executable, str(SCRIPT), "--out", str(tmp_path / "bad"), "Robot/1"],
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert bad.returncode == 2 and "not a valid arpz name" in bad.stderr
    assert not (tmp_path / "bad" / "ca.key").exists()


def test_robot2_cannot_act_as_robot1_and_strangers_cannot_connect(tmp_path: Path) -> None:
    tls = make_fleet_tls(tmp_path / "tls", FLEET, ["robot1", "robot2"], observers=("operator",))
    rogue = make_fleet_tls(tmp_path / "rogue", FLEET, ["robot1"])  # same CN, another CA
    r1 = f"arpz/{FLEET}/robot/robot1"
    r2 = f"arpz/{FLEET}/robot/robot2"
    with secure_ceddp(tmp_path, tls, fleet=FLEET, extra='[hello]\nrelay = "robot2"\n') as (
        server,
        endpoint,
    ):
        # --- strangers: no certificate, a certificate from another CA, plain TCP -----------
        nocert = tmp_path / "nocert.json5"  # trusts the fleet CA but has nothing to show
        nocert.write_text(
            json.dumps(
                {"transport": {"link": {"tls": {"root_ca_certificate": str(tls / "ca.pem")}}}}
            )
        )
        for config, where in (
            (nocert, endpoint),
            (client_config(rogue, "robot1"), endpoint),
            (None, endpoint.replace("tls/", "tcp/")),
        ):
            with pytest.raises(TransportError):
                open_client(where, config, timeout_s=0).close()

        configs = [
            write_secure_robot(
                tmp_path, "robot1", endpoint, client_config(tls, "robot1"),
                fleet=FLEET, preset="machine2", hello=True,
            ),
            write_secure_robot(
                tmp_path, "robot2", endpoint, client_config(tls, "robot2"),
                fleet=FLEET, preset="machine3",
            ),
        ]  # fmt: skip
        spied, observed = Seen(), Seen()
        with (
            robots(tmp_path, configs) as procs,
            open_client(endpoint, client_config(tls, "robot2")) as spy,
            open_client(endpoint, client_config(tls, "robot2")) as forger,
            open_client(endpoint, client_config(tls, "operator")) as observer,
            # a second session: a session's own puts reach its own subscribers without the router
            open_client(endpoint, client_config(tls, "operator")) as observer_writes,
        ):
            spy.subscribe(f"{r1}/**", spied)
            spy.subscribe(f"arpz/{FLEET}/ceddp/stats", spied)
            spy.subscribe(f"{r2}/cmd/**", spied)
            observer.subscribe(f"{r1}/stats", observed)
            wait_until(
                lambda: (
                    "robot robot2 joined" in server.output()
                    and "robot robot1 joined" in server.output()
                ),
                what="both robots joined",
            )
            for key, payload in _forge(r1).items():
                forger.put(key, payload)
            forger.declare_token(f"arpz/{FLEET}/robot/robot9/presence")
            for key, payload in _forge(r1).items():  # the observer certificate is read-only
                observer_writes.put(key, payload)
            # the positive control on the same link, sent last: it must arrive (through the
            # channel, as everything robot2 may send; a plain put would be refused)
            _probe(forger, f"{r2}/sensor/probe", 3)
            wait_until(
                lambda: any(
                    (stats := _stats(p)) is not None and stats.commands_received > 3
                    for p in observed.payloads(f"{r1}/stats")
                ),
                timeout_s=15,
                what="robot1 to act on the CEDDP's Hello commands",
            )
            wait_until(
                lambda: (
                    f"arpz/{FLEET}/ceddp/stats" in spied.seen_keys()
                    and f"{r2}/cmd/hello" in spied.seen_keys()
                ),
                what="the spy to get what robot2 may get",
            )
            settle(1.0)  # deliberately: a second more in which robot1's keys must not reach it
            for proc in procs:
                assert proc.interrupt() == 0, proc.output()
            robot1_out = procs[0].output()
        assert server.interrupt() == 0, server.output()

    # robot 2's certificate reads nothing of robot 1 ...
    assert not [k for k in spied.seen_keys() if k.startswith(r1)], spied.seen_keys()[:10]
    # ... and robot 1 acted on no forged command (only the CEDDP's Hello hops arrived)
    assert "undecodable command" not in robot1_out
    # every report on robot 1's stats key is robot 1's own (the forged one never got through)
    reports = [_stats(p) for p in observed.payloads(f"{r1}/stats")]
    assert reports and None not in reports, "a forged report reached robot 1's stats key"
    last = reports[-1]
    assert last is not None
    assert last.command_decode_errors == 0 and last.commands_received > 0

    summary = json.loads((tmp_path / "summary.json").read_text())
    robot1 = summary["robots"]["robot1"]
    assert "forged" not in robot1["topics"]
    assert robot1["topics"]["pir"]["decode_errors"] == 0
    assert "robot9" not in summary["robots"]
    assert summary["robots"]["robot2"]["topics"]["probe"]["received"] == 3  # positive control
    _reconciles(summary, "robot1")
    _reconciles(summary, "robot2", skip=("probe",))
    hello = robot1["hello"]
    assert hello["received"] > 0 and hello["sent"] == hello["received"] + hello["lost"]


def _probe(session: ZenohTransport, key: str, count: int) -> None:
    """``count`` samples through a reliable-channel writer, once the CEDDP's reader matched."""
    with Writer(session, key, SENSOR_QOS) as writer:
        wait_until(lambda: writer.matched_count > 0, what=f"the CEDDP's reader of {key}")
        for seq in range(1, count + 1):
            writer.write(encode(Sample("robot2:0000000probe", seq, 1, 2.0)))
        assert writer.wait_for_acknowledgments(10.0), f"{key}: probes not acknowledged"


def test_user_password_variant_keeps_strangers_out(tmp_path: Path) -> None:
    tls = make_fleet_tls(tmp_path / "tls", FLEET, ["robot1", "robot2"], usrpwd=True)
    r1 = f"arpz/{FLEET}/robot/robot1"
    with secure_ceddp(tmp_path, tls, fleet=FLEET, variant="-usrpwd") as (server, endpoint):
        wrong = tmp_path / "wrong.json5"
        text = client_config(tls, "robot2", "-usrpwd").read_text()
        password = json.loads(text[text.index("{") :])["transport"]["auth"]["usrpwd"]["password"]
        wrong.write_text(text.replace(password, "not-the-password"))
        with pytest.raises(TransportError):
            open_client(endpoint, wrong, timeout_s=0).close()
        nouser = tmp_path / "nouser.json5"
        nouser.write_text(text.replace('"user": "robot2"', '"user": "robot7"'))
        with pytest.raises(TransportError):
            open_client(endpoint, nouser, timeout_s=0).close()

        config = write_secure_robot(
            tmp_path, "robot1", endpoint, client_config(tls, "robot1", "-usrpwd"),
            fleet=FLEET, preset="machine2",
        )  # fmt: skip
        with (
            robots(tmp_path, [config]) as procs,
            open_client(endpoint, client_config(tls, "robot2", "-usrpwd")) as forger,
        ):
            wait_until(lambda: "robot robot1 joined" in server.output(), what="robot1 joined")
            for key, payload in _forge(r1).items():
                forger.put(key, payload)
            _probe(forger, f"arpz/{FLEET}/robot/robot2/sensor/probe", 2)
            settle(1.0)  # deliberately: a second in which robot1 must not act on a forged command
            assert procs[0].interrupt() == 0, procs[0].output()
            assert "undecodable command" not in procs[0].output()
        assert server.interrupt() == 0, server.output()

    summary = json.loads((tmp_path / "summary.json").read_text())
    assert "forged" not in summary["robots"]["robot1"]["topics"]
    assert summary["robots"]["robot2"]["topics"]["probe"]["received"] == 2
    _reconciles(summary, "robot1")


CHANNEL = '[sensor_qos]\nreliability = "reliable"\nhistory = "keep_last"\ndepth = 50\n'


def test_the_reliable_channel_works_through_the_access_control(tmp_path: Path) -> None:
    """Real deployments run sensor topics through the reliable channel, whose control traffic
    (reader and writer tokens, heartbeats, ACKNACKs) lives on keys below each sensor key: the
    access control must let exactly that through."""
    tls = make_fleet_tls(tmp_path / "tls", FLEET, ["robot1", "robot2"])
    with secure_ceddp(tmp_path, tls, fleet=FLEET, extra=CHANNEL) as (server, endpoint):
        configs = [
            write_secure_robot(
                tmp_path, robot, endpoint, client_config(tls, robot),
                fleet=FLEET, preset=preset, extra=CHANNEL,
            )
            for robot, preset in (("robot1", "machine1"), ("robot2", "machine3"))
        ]  # fmt: skip
        with robots(tmp_path, configs) as procs:
            settle(2.0)  # deliberately: 2 s of the fleet running through the access control
            for proc in procs:
                assert proc.interrupt() == 0, proc.output()
        assert server.interrupt() == 0, server.output()
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["ingest"]["path"] == "reliable channel"
    for robot in ("robot1", "robot2"):
        _reconciles(summary, robot)
        assert summary["robots"][robot]["received"] > 0


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="needs systemd-analyze")
def test_the_systemd_units_verify(tmp_path: Path) -> None:
    """What `systemctl enable` would load: syntax, directives, the robot template's instance."""
    units = ROOT / "deploy" / "systemd"
    made = []
    for source, name in (
        ("arpz-ceddp.service", "arpz-ceddp.service"),
        ("arpz-robot@.service", "arpz-robot@robot1.service"),
    ):
        text = (units / source).read_text().replace("/opt/arpz/venv/bin/python", sys.executable)
        (tmp_path / name).write_text(text)
        made.append(str(tmp_path / name))
    done = subprocess.run(
        ["systemd-analyze", "verify", *made], capture_output=True, text=True, timeout=60
    )
    # it exits 0 even for an unknown directive or value, which it only prints
    assert done.returncode == 0 and not (done.stdout + done.stderr).strip(), done.stderr


def test_robot2_cannot_speak_as_robot1_through_its_own_keys(tmp_path: Path) -> None:
    """Issue 15, item 1: robot 2's certificate may put on robot 2's keys only, but the writer guids
    of robot 1 are in liveliness tokens an observer can read. DATA, heartbeats and GAPs that
    carry robot 1's guids on robot 2's own keys (allowed by the access control) are refused by
    the CEDDP's reader as impersonations: robot 1's counts stay exact."""
    tls = make_fleet_tls(tmp_path / "tls", FLEET, ["robot1", "robot2"], observers=("operator",))
    r1 = f"arpz/{FLEET}/robot/robot1"
    r2 = f"arpz/{FLEET}/robot/robot2"
    with secure_ceddp(tmp_path, tls, fleet=FLEET, extra=CHANNEL) as (server, endpoint):
        configs = [
            write_secure_robot(
                tmp_path, robot, endpoint, client_config(tls, robot),
                fleet=FLEET, preset=preset, extra=CHANNEL,
            )
            for robot, preset in (("robot1", "machine2"), ("robot2", "machine3"))
        ]  # fmt: skip
        writers: list[str] = []
        readers: list[str] = []
        with (
            robots(tmp_path, configs) as procs,
            open_client(endpoint, client_config(tls, "operator")) as observer,
            open_client(endpoint, client_config(tls, "robot2")) as forger,
        ):
            observer.watch_liveliness(f"{r1}/sensor/*/rel/w/*/*", lambda k, _a: writers.append(k))
            observer.watch_liveliness(f"{r1}/sensor/*/rel/r/*/*", lambda k, _a: readers.append(k))
            wait_until(lambda: len(writers) >= 5 and len(readers) >= 5, what="robot1's tokens")
            forged = 0
            for token in list(writers):
                split = wire.split_control_key(token, "w", 2)
                assert split is not None, token
                topic, (writer_hex, _qos) = split
                own = topic.replace(r1, r2, 1)  # the same topic name, under robot 2's keys
                guid = bytes.fromhex(writer_hex)
                ceddp_reader = next(
                    s[1][0]
                    for k in readers
                    if (s := wire.split_control_key(k, "r", 2)) is not None and s[0] == topic
                )
                stamp = time.time_ns()
                for seq in (10**6, 10**6 + 1):
                    forger.put(own, b"\xc1", attachment=wire.encode_data(0, guid, seq, stamp))
                forger.put(
                    wire.heartbeat_key(own, writer_hex),
                    wire.encode_heartbeat(0, guid, 1, 10**12, 1),
                )
                gap = wire.encode_gap(guid, bytes.fromhex(ceddp_reader), [(1, 10**6)])
                for _ in range(5):
                    forger.put(wire.directed_key(own, ceddp_reader), gap)
                forged += 8
            # deliberately 2 s of the robot's stream alongside the forged messages, each to be
            # refused as it comes
            settle(2.0)
            for proc in procs:
                assert proc.interrupt() == 0, proc.output()
        assert server.interrupt() == 0, server.output()
    summary = json.loads((tmp_path / "summary.json").read_text())
    _reconciles(summary, "robot1")
    channel = summary["ingest"]["channel"]
    assert channel["impersonations"] == forged, channel
    assert channel["lost"] == 0 and channel["implausible"] == 0, channel


def test_a_wildcard_put_cannot_reach_a_robots_commands(tmp_path: Path) -> None:
    """Issue 15, item 7: robot 2's certificate puts on key expressions that intersect its own
    ``cmd/**`` (``robot2/*/velocity``, ``robot2/**``): the access control allows a robot exactly
    the keys it writes, so these fall to the default deny and no subscriber of robot 2's
    commands receives them, while its plain sensor put (the positive control) arrives."""
    tls = make_fleet_tls(tmp_path / "tls", FLEET, ["robot1", "robot2"], observers=("operator",))
    r2 = f"arpz/{FLEET}/robot/robot2"
    with secure_ceddp(tmp_path, tls, fleet=FLEET) as (server, endpoint):
        commands, sensors = Seen(), Seen()
        with (
            open_client(endpoint, client_config(tls, "operator")) as observer,
            open_client(endpoint, client_config(tls, "robot2")) as robot2,
        ):
            observer.subscribe(f"{r2}/cmd/**", commands)
            observer.subscribe(f"{r2}/sensor/**", sensors)
            # the positive control first: once robot2's own sensor put arrives, the observer's
            # subscriptions are in place, so a forged command that got through would be seen
            wait_until(
                lambda: bool(sensors.seen_keys()) or robot2.put(f"{r2}/sensor/probe", b"x"),
                timeout_s=10,
                what="robot2's own sensor put (the positive control)",
            )
            payload = encode(Command("ceddp:forged", 1, 1, [9.0, 9.0]))
            for key in (f"{r2}/*/velocity", f"{r2}/**", f"{r2}/c$*/velocity"):
                robot2.put(key, payload)
            settle(0.5)  # deliberately: the time a forged command would take to arrive
        assert server.interrupt() == 0, server.output()
    assert set(sensors.seen_keys()) == {f"{r2}/sensor/probe"}
    assert commands.seen_keys() == [], commands.seen_keys()


def test_an_operator_may_call_a_robots_services_and_an_observer_may_not(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Services under mutual TLS and access control: the operator's certificate calls robot
    1's service (``ServiceCaller`` and ``arpz service call``), the observer's is refused at once
    and its call never reaches the robot (its count stays the operator's calls)."""
    env = {"PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    tls = make_fleet_tls(
        tmp_path / "tls", FLEET, ["robot1"], observers=("observer",), operators=("operator",)
    )
    with secure_ceddp(tmp_path, tls, fleet=FLEET) as (server, endpoint):
        config = write_secure_robot(
            tmp_path, "robot1", endpoint, client_config(tls, "robot1"),
            fleet=FLEET, preset="machine1", rate_hz=5, extra=SERVICES,
        )  # fmt: skip
        with robots(tmp_path, [config], env=env) as (robot,):
            trigger = "std_srvs/srv/Trigger"
            where = ["--connect", endpoint, "--fleet", FLEET]
            capsys.readouterr()
            operator = [*where, "--zenoh-config", str(client_config(tls, "operator"))]
            assert service_main(["call", "/robot1/dock", trigger, *operator]) == 0
            assert 'message: "docked"' in capsys.readouterr().out
            observer = [*where, "--zenoh-config", str(client_config(tls, "observer"))]
            started = time.monotonic()
            assert service_main(["call", "/robot1/dock", trigger, *observer]) == 1
            assert "ServiceRefused: robot1/dock: refused by access control" in (
                capsys.readouterr().err
            )
            assert time.monotonic() - started < 5.0, "refused at once, not after the timeout"
            lamp = ("robot1", "lamp", {"data": True}, 3.0)
            for name in ("operator", "observer"):
                transport = open_client(endpoint, client_config(tls, name))
                try:
                    caller = ServiceCaller(transport, FLEET, access_control=lambda: True)
                    wait_until(lambda c=caller: c.directory("robot1").present is not None)
                    if name == "observer":
                        with pytest.raises(ServiceRefused):
                            caller.call(*lamp, type="std_srvs/srv/SetBool")
                    else:
                        assert caller.call(*lamp, type="std_srvs/srv/SetBool").message == "lamp on"
                    caller.close()
                finally:
                    transport.close()
            assert robot.interrupt() == 0, robot.output()
        assert server.interrupt() == 0, server.output()
    summary = json.loads((tmp_path / "summary.json").read_text())
    served = summary["services"]["robot1"]
    # only the operator's calls reached the robot
    assert (served["dock"]["robot"]["calls"], served["dock"]["robot"]["ok"]) == (1, 1)
    assert (served["lamp"]["robot"]["calls"], served["lamp"]["robot"]["ok"]) == (1, 1)
    _reconciles(summary, "robot1")
